"""The start-up warm-up runs the configured mapping path on a scene that exercises it."""

from __future__ import annotations

import numpy as np
import pytest

from monovoc_ros.core.evidence.palette import UNOBSERVED_ID
from monovoc_ros.core.mapping import MapperConfig, SemanticMapper
from monovoc_ros.core.warm_up import warm_up, warm_up_scene


@pytest.mark.parametrize(
    "config", [MapperConfig(), MapperConfig(semantic_mode="scd"), MapperConfig(mask_ids="per_frame")]
)
def test_the_warm_up_scene_labels_both_objects_in_every_mode(config):
    gaussians, keyframes = warm_up_scene()
    mapper = SemanticMapper(gaussians, config)
    for keyframe in keyframes:
        mapper.integrate(keyframe)
    result = mapper.result()
    assert len(set(result.object_ids[result.object_ids != UNOBSERVED_ID].tolist())) == 2
    assert len(result.objects(gaussians).objects) == 2
    if config.mask_ids == "per_frame":  # the second keyframe was associated with the first one's objects
        assert len(mapper.associator.issued) == 2
    assert warm_up(config) > 0
    assert np.all(np.isfinite(result.confidence))


def test_kernels_count_as_cached_once_their_cache_is_written(tmp_path, monkeypatch):
    from monovoc_ros.core.raster import numba_kernels
    from monovoc_ros.core.warm_up import kernels_cached

    warm_up(MapperConfig())  # compiles (and caches) the tile kernel if this copy had no cache
    assert kernels_cached()
    cache_file = numba_kernels.accumulate_tiles._cache._cache_file
    monkeypatch.setattr(cache_file, "_index_path", str(tmp_path / "absent.nbi"))
    assert not kernels_cached()
    (tmp_path / "absent.nbi").write_bytes(b"an index of another numba")  # stale: numba would compile
    assert not kernels_cached()


def test_a_warm_up_with_a_map_update_readies_every_map_update_kernel():
    """Kernels a large or bent map reaches and the tiny scene's update does not (sampled targets' normals, the
    smooth field's sums) are loaded too, for the types a SLAM map gives them: none is compiled on a first real
    update. (numba's dispatchers list the signatures they hold.)"""
    from monovoc_ros.core.follow import map_follow_kernels
    from monovoc_ros.core.object_geometry_kernels import group_by_object, voxel_keys_by_object

    warm_up(MapperConfig(), map_update=True)
    kernels = (map_follow_kernels.surface_normals_kernel, map_follow_kernels.field_sums)
    assert all(kernel.signatures for kernel in (*kernels, group_by_object, voxel_keys_by_object))
    float32_normals = [sig for sig in map_follow_kernels.surface_normals_kernel.signatures if "float32" in str(sig)]
    assert float32_normals
