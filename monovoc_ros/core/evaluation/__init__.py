"""Scoring and the dataset readers: rendered labels against reference masks (``evaluation``,
``evaluation_kernels``), per-frame maps against reference instances (``instance_eval``), and keyframe
sequences from disk and their views (``datasets``).

May import every other stage (``core.map`` to ``core.follow``) and the root's ``keyframe``; no stage imports it.
"""
