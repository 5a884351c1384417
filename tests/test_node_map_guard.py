"""Map updates that would wipe the map (issue 9, case 3), in a live node: an empty cloud, clouds whose
header lies, and updates removing most of the Gaussians are refused and counted, the map and its
evidence stay; a loop closure that moves every Gaussian (no ids, all evidence dropped) is applied."""

from __future__ import annotations

import numpy as np
import pytest

import msg_adapters as ma
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.map_store import load_snapshot
from monovoc_ros.ros_harness import (
    call_service,
)
from tests.evidence import assert_same_evidence
from tests.node_scene import assemble, offline_mapper, running_mapper, scene_messages, small_scene

pytestmark = pytest.mark.ros


def _empty_cloud(gaussians: GaussianMap):
    return ma.gaussian_map_to_cloud(gaussians.subset(np.zeros(0, np.int64)))


def _lying_cloud(gaussians: GaussianMap, **header):
    msg = ma.gaussian_map_to_cloud(gaussians)
    for key, value in header.items():
        if key == "count":
            msg.fields[3].count = value
        else:
            setattr(msg, key, value)
    return msg


def test_map_updates_that_would_wipe_the_map_are_refused(tmp_path):
    from monovoc_interfaces.srv import SaveMap

    scene, messages = small_scene(), scene_messages()
    gaussians = scene.gaussians
    n = len(gaussians)
    keyframes = assemble(messages[:4])
    reference = offline_mapper(gaussians, keyframes)
    rng = np.random.default_rng(3)
    # (cloud, the counter it must raise)
    refused = [
        (_empty_cloud(gaussians), "rejected.empty_gaussians"),
        (_lying_cloud(gaussians, count=0), "rejected.bad_gaussians"),
        (_lying_cloud(gaussians, row_step=2**32 - 1), "rejected.bad_gaussians"),
        (ma.gaussian_map_to_cloud(gaussians.subset(np.sort(rng.choice(n, n // 3, replace=False)))),
         "rejected.map_shrink"),  # by id: two thirds removed
        (ma.gaussian_map_to_cloud(gaussians.subset(np.arange(n // 4)), include_ids=False),
         "rejected.map_shrink"),  # by count: three quarters removed
    ]  # fmt: skip
    moved = GaussianMap(
        gaussians.means + np.float32(0.05), gaussians.scales, gaussians.quats, gaussians.opacities, gaussians.colors
    )
    params = {"publish_rate_hz": 0.0, "diagnostics_period_s": 0.2}
    with running_mapper(tmp_path, params) as mapper:
        node, diagnostics, publisher, save = mapper.node, mapper.diagnostics, mapper.publisher, mapper.save
        publisher.publish_map(gaussians)
        for msgs in messages[:4]:
            publisher.publish_messages(msgs)
        first = diagnostics.wait_for(
            lambda v: v["keyframes_processed"] == "4" and v["queue_length"] == "0" and v["observed_gaussians"] != "0",
            20.0,
            process=node,
        )
        counts: dict[str, int] = {}
        for cloud, counter in refused:
            counts[counter] = counts.get(counter, 0) + 1
            publisher.gaussians.publish(cloud)  # one at a time: the latched topic keeps only the newest
            diagnostics.wait_for(lambda v, c=counter, k=counts[counter]: v.get(c) == str(k), 10.0, process=node)
        done = diagnostics.wait_for(lambda v: v["gaussians"] == str(n), 5.0, process=node)
        assert done["map_updates"] == "0" and done["observed_gaussians"] == first["observed_gaussians"]
        assert call_service(save, SaveMap.Request(directory=str(tmp_path / "kept")), process=node).success

        # A loop closure without ids: every Gaussian moved 5 cm (beyond the 1 cm reassociation tolerance).
        publisher.gaussians.publish(ma.gaussian_map_to_cloud(moved, include_ids=False))
        after = diagnostics.wait_for(lambda v: v["map_updates"] == "1", 10.0, process=node)
        assert after["gaussians"] == str(n)
        # The counters above come before each warning is written: wait for the text, do not assume it.
        for text in ("removes 20000 of 30000 Gaussians (67% > map_update_max_shrink 0.5)",
                     "it has no Gaussians (the map in use is kept)", "field 'scale_0' has count 0"):  # fmt: skip
            node.wait_for_output(text, 10.0)
        node.check_running()
    kept = load_snapshot(tmp_path / "kept")
    assert len(kept.gaussians) == n and kept.n_keyframes == 4
    assert_same_evidence(kept.state, reference.state)
