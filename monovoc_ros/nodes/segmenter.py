"""The `segmenter` node: keyframe images in, per-frame instance masks and their class names out.

    ros2 run monovoc_ros segmenter [--ros-args -p model:=/path/to/yolo-seg.onnx]   # in /monovoc, as the mapper

Subscribes to `image` (CompressedImage or, with `image_transport: raw`, Image) and publishes, with the
image's header, `mask` (sensor_msgs/Image mono16: instance ids numbered per image, 0 = void) and
`segments` (monovoc_interfaces/SegmentArray: per id a class name and score), which the mapper takes with
`mask_transport: raw`, `mask_ids: per_frame` and `use_segments: true` (the launch file's `segmenter:=true`).
When segmenting is slower than the images come, the newest image waits in a one-slot mailbox and older
ones are dropped and counted; images that cannot be decoded are refused and counted (diagnostics), never
fatal. A missing, corrupt or unrecognized model stops the node at start with one line.
"""

from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

import msg_adapters as ma
from monovoc_ros.contract import (
    DEFAULT_NAMESPACE,
    DIAGNOSTICS_TOPIC,
    IMAGE_MESSAGE_TYPES,
    SEGMENTS_TYPE,
    message_class,
)
from monovoc_ros.nodes.mapping_node import StopSignals
from monovoc_ros.nodes.param_spec import Param, ParameterError, declare
from monovoc_ros.nodes.qos import DIAGNOSTICS_QOS, input_qos
from monovoc_ros.nodes.startup import init_rclpy
from monovoc_ros.segment.backend import SegmenterModelError, load_segmenter
from monovoc_ros.segment.model_files import CHECKPOINTS, DEFAULT_MODEL
from monovoc_ros.segment.options import OPTION_SPECS, SegmenterOptions, option_defaults, parse_class_map

NODE_NAME = "segmenter"
# Camera images: far beyond any keyframe camera, and a decompression bomb is refused before decoding.
MAX_IMAGE_PIXELS = 4096 * 4096


def _option_params() -> tuple[Param, ...]:
    defaults = option_defaults()
    return tuple(Param(s.name, defaults[s.name], s.description, low=s.low, high=s.high) for s in OPTION_SPECS)


PARAMS: tuple[Param, ...] = (
    Param("model", DEFAULT_MODEL, f"{' or '.join(CHECKPOINTS)} (exported at install) or a YOLO-seg .onnx file"),
    Param("names_file", "", "class names (txt one per line, JSON, YAML); empty: the model's metadata"),
    Param("class_map", "", "renames, 'dining table=table;person=' ('CLASS=' drops a class)"),
    Param(
        "image_transport",
        "compressed",
        "'compressed' (CompressedImage) or 'raw' (Image) on `image`",
        choices=tuple(IMAGE_MESSAGE_TYPES),
    ),
    Param("threads", 2, "onnxruntime intra-op threads", low=1, high=64),
    Param("input_depth", 10, "keep-last depth of the image subscription", low=1, high=10000),
    Param("diagnostics_period_s", 1.0, "period of /diagnostics", above=0.0, high=3600.0),
    *_option_params(),
)


@dataclass
class SegmenterStats:
    lock: threading.Lock = field(default_factory=threading.Lock)
    received: int = 0
    segmented: int = 0
    dropped: int = 0  # replaced in the mailbox by a newer image before being segmented
    bad_images: int = 0
    errors: int = 0
    instances_last: int = 0
    ms_last: float = 0.0
    ms_total: float = 0.0

    def snapshot(self) -> dict[str, Any]:
        with self.lock:
            values = {k: v for k, v in self.__dict__.items() if k != "lock"}
        values["ms_mean"] = values.pop("ms_total") / max(1, values["segmented"])
        return values


class SegmenterNode(Node):
    def __init__(self) -> None:
        super().__init__(NODE_NAME, namespace=DEFAULT_NAMESPACE)  # the mapper's, unless remapped (__ns)
        values = declare(self, PARAMS)
        options = SegmenterOptions(
            **{s.name: values[s.name] for s in OPTION_SPECS},
            class_map=parse_class_map([item for item in values["class_map"].split(";") if item.strip()]),
        )
        self.segmenter = load_segmenter(
            model=values["model"], options=options, names_file=values["names_file"] or None, threads=values["threads"]
        )
        self.stats = SegmenterStats()
        self.compressed = values["image_transport"] == "compressed"
        image_type = message_class(IMAGE_MESSAGE_TYPES[values["image_transport"]])
        self.mask_pub = self.create_publisher(message_class(IMAGE_MESSAGE_TYPES["raw"]), "mask", input_qos(100))
        self.segments_pub = self.create_publisher(message_class(SEGMENTS_TYPE), "segments", input_qos(100))
        self.diag_pub = self.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, DIAGNOSTICS_QOS)
        self._mailbox: Any = None
        self._wake = threading.Condition()
        self._stopping = False
        self.create_subscription(image_type, "image", self._on_image, input_qos(values["input_depth"]))
        self.create_timer(values["diagnostics_period_s"], self._publish_diagnostics)
        self._worker = threading.Thread(target=self._work, name="segmenter", daemon=True)
        self.get_logger().info(
            f"ready: {self.get_namespace()} image ({values['image_transport']}) -> mask (mono16) + segments; model "
            f"{self.segmenter.path.name} ({self.segmenter.layout} layout, {len(self.segmenter.class_names)} classes)"
        )

    def start(self) -> None:
        self._worker.start()

    def stop(self) -> None:
        with self._wake:
            self._stopping = True
            self._wake.notify_all()
        self._worker.join(timeout=10.0)

    def _on_image(self, msg: Any) -> None:
        with self.stats.lock:
            self.stats.received += 1
        with self._wake:
            if self._mailbox is not None:
                with self.stats.lock:
                    self.stats.dropped += 1
            self._mailbox = msg  # the newest image wins
            self._wake.notify()

    def _work(self) -> None:
        while True:
            with self._wake:
                while self._mailbox is None and not self._stopping:
                    self._wake.wait()
                if self._stopping:
                    return
                msg, self._mailbox = self._mailbox, None
            self._segment(msg)

    def _decode(self, msg: Any):
        if self.compressed:
            rgb = ma.compressed_image_to_numpy(msg, max_pixels=MAX_IMAGE_PIXELS)
        else:
            pixels = int(msg.height) * int(msg.width)
            if pixels > MAX_IMAGE_PIXELS:  # refused before its buffer is viewed, as compressed ones are
                raise ma.AdapterError(f"Image: {msg.width}x{msg.height} is more than {MAX_IMAGE_PIXELS} pixels")
            rgb = ma.image_to_numpy(msg)
        if rgb.ndim != 3 or rgb.dtype.name != "uint8":
            raise ma.AdapterError(f"expected an 8-bit color image, got shape {rgb.shape} {rgb.dtype}")
        return rgb

    def _segment(self, msg: Any) -> None:
        try:
            rgb = self._decode(msg)
        except (ma.AdapterError, ValueError) as exc:
            with self.stats.lock:
                self.stats.bad_images += 1
            self.get_logger().warning(f"image refused: {exc}", throttle_duration_sec=5.0)
            return
        t0 = time.perf_counter()
        try:
            segmentation = self.segmenter.segment(rgb)
        except (SegmenterModelError, ValueError) as exc:
            with self.stats.lock:
                self.stats.errors += 1
            self.get_logger().error(f"segmenting failed: {exc}", throttle_duration_sec=5.0)
            return
        ms = 1e3 * (time.perf_counter() - t0)
        stamp, frame_id = ma.time_to_ns(msg.header.stamp), msg.header.frame_id
        # Segments first: the mapper pairs them with the mask by stamp, and the mask completes a keyframe.
        self.segments_pub.publish(ma.segment_array(segmentation.labels(), frame_id=frame_id, stamp=stamp))
        self.mask_pub.publish(ma.numpy_to_image(segmentation.ids, "mono16", frame_id=frame_id, stamp=stamp))
        with self.stats.lock:
            self.stats.segmented += 1
            self.stats.instances_last = segmentation.count
            self.stats.ms_last = ms
            self.stats.ms_total += ms

    def _publish_diagnostics(self) -> None:
        values = self.stats.snapshot()
        if values["bad_images"] or values["errors"]:
            level, message = DiagnosticStatus.WARN, f"{values['bad_images']} bad images, {values['errors']} errors"
        elif values["dropped"]:
            level, message = (
                DiagnosticStatus.OK,
                f"{values['segmented']} segmented, {values['dropped']} dropped (newest wins)",
            )
        else:
            level, message = DiagnosticStatus.OK, f"{values['segmented']} segmented"
        status = DiagnosticStatus(
            level=level,
            name=f"{self.get_namespace().rstrip('/')}/{NODE_NAME}",
            hardware_id=self.segmenter.path.name,
            message=message,
            values=[KeyValue(key=k, value=f"{v:.3f}" if isinstance(v, float) else str(v)) for k, v in values.items()],
        )
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diag_pub.publish(msg)


def main(args: list[str] | None = None) -> int:
    stop = StopSignals(NODE_NAME)
    try:
        init_rclpy(args)
    except ValueError as exc:
        print(f"{NODE_NAME}: cannot start: {exc}", file=sys.stderr)
        return 1
    try:
        node = SegmenterNode()
    except ParameterError as exc:
        print(f"{NODE_NAME}: invalid parameter {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    except (SegmenterModelError, ValueError, OSError) as exc:
        print(f"{NODE_NAME}: cannot start: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 1
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    node.start()
    try:
        stop.spin(executor)
    finally:
        node.stop()
        executor.shutdown(timeout_sec=5.0)
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
