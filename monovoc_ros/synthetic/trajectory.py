"""A smooth camera loop through the room that looks around at every wall, the floor and the furniture.

The camera circles the room's free centre (above the table and chair backs) once, looking across the
room at a target that runs along the walls and moves up and down, so every object on the floor, the
furniture, the walls and the ceiling comes into view. Poses are camera-to-world in the OpenCV optical
frame (x right, y down, z forward) with the image never rolled against world z (up).
"""

from __future__ import annotations

import numpy as np

from monovoc_ros.synthetic.errors import SyntheticError

_UP = np.array([0.0, 0.0, 1.0])


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = _UP) -> np.ndarray:
    """Camera-to-world pose (4x4, OpenCV optical axes) of a camera at ``eye`` looking at ``target``."""
    forward = np.asarray(target, float) - np.asarray(eye, float)
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    norm = np.linalg.norm(right)
    if norm < 1e-9:
        raise SyntheticError("look_at: viewing direction is parallel to the up vector")
    right /= norm
    down = np.cross(forward, right)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = right, down, forward, eye
    return T


def camera_loop(n: int, phase: float = 0.0) -> np.ndarray:
    """(n, 4, 4) poses evenly spaced along one closed loop; ``phase`` (radians) shifts the start."""
    if n < 1:
        raise SyntheticError(f"need at least one keyframe, got {n}")
    theta = phase + 2 * np.pi * np.arange(n) / n
    eye = np.stack([1.25 * np.cos(theta), 0.8 * np.sin(theta), 1.45 + 0.15 * np.sin(2 * theta)], axis=1)
    # Look across the room; sweep the gaze sideways and between the floor and the ceiling line.
    gaze = theta + np.pi + 0.55 * np.sin(3 * theta)
    target = np.stack([2.8 * np.cos(gaze), 2.3 * np.sin(gaze), 0.75 + 0.7 * np.sin(5 * theta + 0.4)], axis=1)
    return np.stack([look_at(e, t) for e, t in zip(eye, target, strict=True)])
