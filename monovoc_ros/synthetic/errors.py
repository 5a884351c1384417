"""The error type of the synthetic scene package."""


class SyntheticError(ValueError):
    """An invalid synthetic scene configuration, input array or request; the message says what is wrong."""
