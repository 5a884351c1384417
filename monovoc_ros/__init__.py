"""monovoc_ros: open-vocabulary object-level semantic mapping on 3D Gaussian Splatting maps."""

__version__ = "0.1.0"
