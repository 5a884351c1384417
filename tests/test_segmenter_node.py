"""The segmenter node as a robot with only a camera runs it: `ros2 launch ... segmenter:=true` and a bag replayed
without its masks. The segmenter's mono16 masks and segment names reach the mapper with the images' stamps and
every mask it made is integrated; corrupt images are refused and counted while the node keeps segmenting; a bad
model file stops the node at start with one line."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest

from monovoc_ros.bags import bag_info
from monovoc_ros.contract import CAMERA_FRAME
from monovoc_ros.embed import default_model_dir
from monovoc_ros.ros_harness import ClientNode, DiagnosticsMonitor, HarnessError, NodeProcess, wait_until
from tests.rosutil import REPO, ros_environment

pytestmark = [pytest.mark.ros, pytest.mark.slow]

BAG = REPO / "bags" / "synthetic_room.mcap"
KEYFRAMES = bag_info(BAG).topics["/monovoc/image"].count
LAUNCH = "ros2 launch monovoc_ros monovoc.launch.py segmenter:=true executable:=mapping_node"


@pytest.fixture()
def env(tmp_path) -> dict:
    if shutil.which("ros2") is None:
        pytest.fail("no `ros2` on PATH: scripts/install.sh installs it from ../shared/ros2_tools")
    return ros_environment(tmp_path, extra={"MONOVOC_MODEL_DIR": str(default_model_dir())})


def test_launch_with_the_segmenter_on_a_bag_without_masks(env):
    from sensor_msgs.msg import CompressedImage, Image

    from monovoc_interfaces.msg import SegmentArray

    process = NodeProcess(["bash", "-c", "exec " + LAUNCH], env, name="launch_segmenter", cwd=REPO, process_group=True)
    with process, ClientNode(env) as client:
        masks, segments = {}, {}
        outputs = [
            client.node.create_subscription(Image, "/monovoc/mask", lambda m: masks.__setitem__(_ns(m), m), 100),
            client.node.create_subscription(
                SegmentArray, "/monovoc/segments", lambda m: segments.__setitem__(_ns(m), m), 100
            ),
        ]
        segmenter = DiagnosticsMonitor(client.node, "segmenter")
        mapper = DiagnosticsMonitor(client.node, "semantic_mapper")
        segmenter.wait_for(lambda v: "segmented" in v, 120.0, process=process)
        # This client hears every mask only once it has discovered the segmenter's publishers.
        wait_until(lambda: all(s.get_publisher_count() >= 1 for s in outputs), 30.0, "the segmenter's outputs")
        # A bag without masks: the mapper sees only the segmenter's. 2 keyframes/s, a SLAM's pace.
        topics = " ".join(f"/monovoc/{role}" for role in ("image", "camera_info", "pose", "gaussians"))
        replay = f"monovoc replay {BAG} --rate 0.2 --topics {topics}"
        played = subprocess.run(["bash", "-c", replay], env=env, cwd=REPO, capture_output=True, text=True, timeout=180)
        assert played.returncode == 0, played.stdout + played.stderr

        # The replay has ended. Once every image that arrived is segmented or was replaced by a newer one (images
        # published before the segmenter discovered the replay, which waits for the mapper only, never arrive),
        # this client holds every mask and its segments, and the mapper has taken every mask: integrated, or
        # refused as void_mask when nothing was detected (all void). One joint condition: counters read at
        # different moments could pair an image still in flight with a stale count.
        def settled() -> bool:
            seg, mapped = segmenter.values(), mapper.values()
            if not seg or not mapped:
                return False
            made = int(seg["segmented"])
            return (
                made + int(seg["dropped"]) == int(seg["received"]) >= KEYFRAMES * 3 // 4
                and len(masks) == len(segments) == made
                and int(mapped["keyframes_processed"]) + int(mapped["rejected.void_mask"]) == made
            )

        try:
            wait_until(settled, 90.0, "every image segmented, its mask and segments heard and mapped", process=process)
        except HarnessError as exc:
            heard = f"masks heard {len(masks)}, segments heard {len(segments)}"
            raise HarnessError(f"{exc}\n{heard}\nsegmenter {segmenter.values()}\nmapper {mapper.values()}") from None
        done, mapped = segmenter.values(), mapper.values()
        made = int(done["segmented"])
        assert done["bad_images"] == "0" and made >= KEYFRAMES // 2, done  # at this pace nearly none is dropped
        assert int(mapped["keyframes_processed"]) >= made // 2, mapped
        assert mapped["rejected_total"] == mapped["rejected.void_mask"], mapped
        # Each mask and its segments carry an image's stamp and frame; ids are per-frame instance ids.
        recorded = {s for s in _image_stamps()}
        assert set(masks) <= recorded and set(segments) == set(masks)
        for stamp, mask in masks.items():
            assert mask.encoding == "mono16" and mask.header.frame_id == CAMERA_FRAME
            ids = {s.id for s in segments[stamp].segments}
            assert ids == set(range(1, len(ids) + 1))
        # A corrupt and an empty image: refused, counted, and the node goes on segmenting.
        publisher = client.node.create_publisher(CompressedImage, "/monovoc/image", 10)
        wait_until(lambda: publisher.get_subscription_count() >= 2, 20.0, "the image subscribers")
        for count, bad in enumerate((b"\xff\xd8 not a jpeg at all", b""), start=1):
            # One at a time: the one-slot mailbox lets a newer image replace an unread one.
            publisher.publish(CompressedImage(format="jpeg", data=bad))
            segmenter.wait_for(lambda v, n=count: v["bad_images"] == str(n), 30.0, process=process)
        assert process.running(), process.describe()
        assert process.stop() == 0, process.describe()
    assert "Traceback" not in process.output()


def _ns(msg) -> int:
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def _image_stamps() -> list[int]:
    from monovoc_ros.bags import iter_messages

    return [_ns(m.decode()) for m in iter_messages(BAG, ["/monovoc/image"])]


@pytest.mark.parametrize("model", ["absent.onnx", "garbage.onnx"])
def test_a_bad_model_stops_the_node_at_start_with_one_line(env, tmp_path, model):
    (tmp_path / "garbage.onnx").write_bytes(b"\x08\x01 definitely not protobuf" * 10)
    done = subprocess.run(
        [sys.executable, "-m", "monovoc_ros.nodes.segmenter", "--ros-args", "-p", f"model:={tmp_path / model}"],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 1
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("segmenter: cannot start: segmenter model"), done.stderr
