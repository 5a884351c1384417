"""Subcommands of the `monovoc` command line, one module each."""
