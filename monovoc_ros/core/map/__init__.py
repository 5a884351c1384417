"""The SLAM's geometry: the Gaussian map (``gaussians``), PLY files (``ply``), cameras and poses (``camera``).

The first stage: imports nothing else from core.
"""
