"""YOLO-seg as exported to ONNX, run by onnxruntime: the segmenter's first backend."""

from __future__ import annotations

import ast
import json
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from monovoc_ros.core.thread_pools import single_threaded_blas
from monovoc_ros.embed.model_store import ModelMissingError
from monovoc_ros.embed.onnx_session import DEFAULT_THREADS, make_session
from monovoc_ros.segment.backend import SegmenterModelError
from monovoc_ros.segment.letterbox import Letterbox
from monovoc_ros.segment.model_files import DEFAULT_MODEL, resolve_model
from monovoc_ros.segment.options import SegmenterOptions
from monovoc_ros.segment.segmentation import Segmentation
from monovoc_ros.segment.yolo_decode import ModelLayoutError, decode, detect_layout

DEFAULT_STRIDE = 32
single_threaded_blas()  # the mask decoding's matmul would leave BLAS threads spinning on onnxruntime's cores


def first_line(exc: Exception) -> str:
    """onnxruntime's messages run over many lines: the first says what went wrong."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def parse_names(value: object, where: str) -> tuple[str, ...]:
    """Class names from a list, or a dict of index -> name (``yolo export`` metadata, coco.yaml ``names``)."""
    if isinstance(value, Mapping) and "names" in value:
        value = value["names"]
    if isinstance(value, Mapping):
        try:
            indexed = {int(k): str(v) for k, v in value.items()}
        except (TypeError, ValueError):
            raise SegmenterModelError(f"{where}: class names must be keyed by index") from None
        if sorted(indexed) != list(range(len(indexed))):
            raise SegmenterModelError(f"{where}: class name indices must be 0..{len(indexed) - 1}")
        return tuple(indexed[i] for i in range(len(indexed)))
    if isinstance(value, list | tuple) and all(isinstance(v, str) for v in value):
        return tuple(value)
    raise SegmenterModelError(f"{where}: expected a list of class names or a dict index -> name")


def read_names_file(path: str | Path) -> tuple[str, ...]:
    """Class names from a text file (one per line), JSON or YAML (a list, a dict, or coco.yaml's ``names``)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise SegmenterModelError(f"class names file {path}: {exc}") from None
    if path.suffix.lower() == ".json":
        try:
            return parse_names(json.loads(text), str(path))
        except json.JSONDecodeError as exc:
            raise SegmenterModelError(f"class names file {path}: {exc}") from None
    if path.suffix.lower() in (".yaml", ".yml"):
        import yaml

        try:
            return parse_names(yaml.safe_load(text), str(path))
        except yaml.YAMLError as exc:
            raise SegmenterModelError(f"class names file {path}: not YAML ({exc})") from None
    names = tuple(line.strip() for line in text.splitlines() if line.strip())
    if not names:
        raise SegmenterModelError(f"class names file {path} holds no names")
    return names


class YoloSegOnnx:
    """A YOLO-seg ONNX model: one ``images`` input (1, 3, H, W) float in [0, 1], predictions + prototypes out.

    ``model`` is a default model's name (``yolov5s-seg``, ``yolov7-seg``: exported at install) or a path
    to a user's ``.onnx``. Class names come from ``names_file`` or else the model's ``names`` metadata.
    A fixed-size input is letterboxed to its size; a dynamic one runs rectangular at ``input_size``.
    The model is run once on a blank image at construction, so a file that is not a YOLO-seg model fails
    here, with one line, rather than on the first keyframe.
    """

    name = "yolo_onnx"

    def __init__(
        self,
        model: str | Path = DEFAULT_MODEL,
        *,
        options: SegmenterOptions | None = None,
        names_file: str | Path | None = None,
        threads: int = DEFAULT_THREADS,
        model_dir: Path | None = None,
        prefer_cuda: bool = True,
    ) -> None:
        self.options = options if options is not None else SegmenterOptions()
        try:
            self.path = resolve_model(str(model), model_dir)
        except ModelMissingError as exc:
            raise SegmenterModelError(str(exc)) from None
        try:
            self.session = make_session(self.path, threads, prefer_cuda=prefer_cuda)
        except Exception as exc:  # onnxruntime raises its own exception types for unreadable graphs
            raise SegmenterModelError(
                f"segmenter model {self.path} cannot be loaded by onnxruntime: {first_line(exc)}"
            ) from None
        inputs = self.session.get_inputs()
        if len(inputs) != 1 or len(inputs[0].shape) != 4 or inputs[0].shape[1] not in (3, "3", None):
            shapes = [(i.name, i.shape) for i in inputs]
            raise SegmenterModelError(
                f"segmenter model {self.path}: expected one (1, 3, H, W) image input, got {shapes}"
            )
        self.input_name = inputs[0].name
        h, w = inputs[0].shape[2], inputs[0].shape[3]
        self.fixed_input = (h, w) if isinstance(h, int) and isinstance(w, int) and h > 0 and w > 0 else None
        meta = self.session.get_modelmeta().custom_metadata_map
        self.class_names = self._class_names(meta, names_file)
        try:
            self.stride = int(ast.literal_eval(meta["stride"])) if "stride" in meta else DEFAULT_STRIDE
        except (ValueError, SyntaxError):
            raise SegmenterModelError(f"segmenter model {self.path}: unreadable stride metadata") from None
        self.layout = self._check_layout()

    def _class_names(self, meta: Mapping[str, str], names_file: str | Path | None) -> tuple[str, ...]:
        if names_file:
            return read_names_file(names_file)
        if "names" not in meta:
            return ()
        try:
            value = ast.literal_eval(meta["names"])
        except (ValueError, SyntaxError):
            raise SegmenterModelError(f"segmenter model {self.path}: unreadable 'names' metadata") from None
        return parse_names(value, f"{self.path} metadata 'names'")

    def _check_layout(self) -> str:
        blank = np.zeros((self.stride * 4, self.stride * 4, 3), np.uint8)
        outputs = self._run(self.letterbox(*blank.shape[:2]), blank)
        try:
            shapes = [tuple(np.shape(o)) for o in outputs]
            layout, _, _ = detect_layout(shapes, len(self.class_names) if self.class_names else None)
        except ModelLayoutError as exc:
            raise SegmenterModelError(f"segmenter model {self.path}: {exc}") from None
        return layout

    def letterbox(self, height: int, width: int) -> Letterbox:
        if self.fixed_input is not None:
            return Letterbox.fit(height, width, *self.fixed_input)
        return Letterbox.rect(height, width, self.options.input_size, self.stride)

    def _run(self, lb: Letterbox, rgb: np.ndarray) -> list[np.ndarray]:
        try:
            return self.session.run(None, {self.input_name: lb.apply(rgb)})
        except Exception as exc:  # onnxruntime's own types: shape or type errors inside the graph
            raise SegmenterModelError(f"segmenter model {self.path} failed to run: {first_line(exc)}") from None

    def segment(self, rgb: np.ndarray) -> Segmentation:
        """(H, W, 3) uint8 RGB -> instances at the image's resolution."""
        if not (isinstance(rgb, np.ndarray) and rgb.ndim == 3 and rgb.shape[2] == 3 and rgb.dtype == np.uint8):
            raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {getattr(rgb, 'shape', None)}")
        if rgb.shape[0] < 1 or rgb.shape[1] < 1:
            raise ValueError(f"empty image {rgb.shape}")
        lb = self.letterbox(*rgb.shape[:2])
        return decode(self._run(lb, rgb), lb, self.class_names, self.options)
