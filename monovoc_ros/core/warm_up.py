"""The mapper's compiled kernels loaded before the first keyframe needs them.

A new process loads each numba kernel from the on-disk cache on its first call (~1 s for the whole
mapping path; 25 s to compile into an empty cache). In a live node that cost landed on the first
keyframes: measured at 2 keyframes/s, the first took 1.0 s and the second 0.5 s to reach the semantic
cloud, against ~0.2 s afterwards. `warm_up` runs the configured mapping path (votes or SCD, pixel labels,
snapping, per-frame association, labelling, object geometry) once on a tiny scene, so the node can do it
before it subscribes to its inputs; `warm_up_all` (`monovoc warm-up`, run at install) fills the cache for
every path.
"""

from __future__ import annotations

import time

import numpy as np

from monovoc_ros.core.follow.map_motion import warm_up_kernels
from monovoc_ros.core.follow.map_updater import update_map
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.camera import Intrinsics
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.mapping import MapperConfig, SemanticMapper


def warm_up_scene() -> tuple[GaussianMap, list[Keyframe]]:
    """64 Gaussians on a plane 2 m ahead, seen twice at 32x24 by a mask of two objects and a blended pixel."""
    rng = np.random.default_rng(0)
    n = 64
    means = np.column_stack([rng.uniform(-0.6, 0.6, (n, 2)), np.full(n, 2.0)]).astype(np.float32)
    gaussians = GaussianMap(
        means=means,
        scales=np.full((n, 3), 0.08, np.float32),
        quats=np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1)),
        opacities=np.full(n, 0.9, np.float32),
    )
    intrinsics = Intrinsics(20.0, 20.0, 15.5, 11.5, 32, 24)
    mask = np.full((24, 32, 3), 255, np.uint8)
    mask[:, :16] = (200, 30, 30)
    mask[:, 16:] = (30, 30, 200)
    mask[10, 15:17] = (115, 30, 115)  # a blended boundary pixel: the snapping path
    keyframes = [Keyframe(i, (i + 1) * 1_000_000, np.eye(4), intrinsics, mask) for i in range(2)]
    return gaussians, keyframes


def kernels_cached() -> bool:
    """Whether the main tile kernel has entries in numba's on-disk cache that fit this copy of the code (an
    index written for another source file or numba version reads as empty). Loading cached kernels takes
    ~1 s; compiling an empty cache takes 25 s or more, which a node does in a child process (nodes.startup):
    numba cannot be interrupted while it compiles."""
    from monovoc_ros.core.raster import numba_kernels

    try:
        cache_file = numba_kernels.accumulate_tiles._cache._cache_file
    except AttributeError:  # another numba: assume cached and warm up
        return True
    try:
        return bool(cache_file._load_index())
    except Exception:  # an unreadable index: numba would compile
        return False


def warm_up(config: MapperConfig, *, map_update: bool = False) -> float:
    """Runs `config`'s mapping path once on a tiny scene (and a map update without ids: the map-following
    kernels); returns the seconds it took."""
    start = time.perf_counter()
    gaussians, keyframes = warm_up_scene()
    mapper = SemanticMapper(gaussians, config)
    for keyframe in keyframes:
        mapper.integrate(keyframe)
    mapper.result().objects(gaussians)
    if map_update:
        order = np.random.default_rng(1).permutation(len(gaussians))
        moved = GaussianMap(
            means=gaussians.means[order] + np.float32(0.002),
            scales=gaussians.scales[order],
            quats=gaussians.quats[order],
            opacities=gaussians.opacities[order],
        )
        update_map(mapper, moved)
        mapper.result().objects(moved)
        warm_up_kernels()
    return time.perf_counter() - start


# Every mapping path a node can be configured for: compiling them all fills numba's cache for any config.
ALL_PATHS = (MapperConfig(), MapperConfig(mask_ids="per_frame"), MapperConfig(semantic_mode="scd"))


def warm_up_all() -> float:
    """Compiles (into numba's on-disk cache) or loads every mapping path and map updates; returns seconds."""
    return sum(warm_up(config, map_update=True) for config in ALL_PATHS)
