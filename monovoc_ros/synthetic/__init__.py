"""Replica-like synthetic sequences: an analytic furnished room, its Gaussian map, camera loop and masks.

Masks, depth and RGB are ray cast from the analytic surfaces, independent of the Gaussian map; see
``scene`` for the API and ``layout`` for the world frame (metres, z up, floor at z = 0).
"""

from monovoc_ros.synthetic.errors import SyntheticError
from monovoc_ros.synthetic.scene import (
    FLOATER,
    UNLABELLED,
    VARIANTS,
    SceneConfig,
    SceneObject,
    SyntheticScene,
    ViewRender,
    generate_scene,
)

__all__ = [
    "FLOATER",
    "UNLABELLED",
    "VARIANTS",
    "SceneConfig",
    "SceneObject",
    "SyntheticError",
    "SyntheticScene",
    "ViewRender",
    "generate_scene",
]
