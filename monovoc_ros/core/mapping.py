"""The semantic mapper: keyframes in, per-Gaussian object labels out (no ROS).

One class drives the whole method for a Gaussian map: SCD accumulation per keyframe, the palette seen
so far, quantization, and map updates from the SLAM front-end. The offline `monovoc map` command and the
live `semantic_mapper` node both wrap this class, so a bag processed offline and the same bag replayed
through the node give the same semantic map.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from monovoc_ros.core.gaussians import GaussianMap
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.palette import UNOBSERVED_ID, VOID_RGB, Palette, PaletteBuilder
from monovoc_ros.core.quantize import METRICS, Quantization, confidence, quantize
from monovoc_ros.core.raster import IMPLEMENTATIONS, WEIGHT_POWERS, accumulate
from monovoc_ros.core.state import SemanticState, reindex_by_position

VOID_POLICIES = ("skip", "include")


class DuplicateKeyframeError(ValueError):
    """A keyframe whose stamp was already integrated (its evidence would count twice)."""


@dataclass
class MapperConfig:
    impl: str = "numba"  # rasterizer implementation (core.raster.IMPLEMENTATIONS)
    device: str | None = None  # torch device when impl == "torch"
    metric: str = "cmc"  # palette quantization metric (core.quantize.METRICS)
    # Void (pure white) mask pixels: "skip" adds no evidence from them (they are "don't know", not an
    # object); "include" treats white like a color, pulling partly-void Gaussians toward white.
    void_policy: str = "skip"
    # Map updates without stable ids: evidence follows a Gaussian to its new position only when old and
    # new positions are mutual nearest neighbours within this distance (metres).
    reassociation_tolerance: float = 0.01
    # Exponent k of the evidence weights w_ip^k (core.raster.WEIGHT_POWERS): 1 is the paper's SCD; 4 cut
    # the labelling errors at object boundaries most (README, "Choices").
    weight_power: int = 4

    def __post_init__(self) -> None:
        if self.impl not in IMPLEMENTATIONS:
            raise ValueError(f"impl must be one of {IMPLEMENTATIONS}, got {self.impl!r}")
        if self.metric not in METRICS:
            raise ValueError(f"metric must be one of {METRICS}, got {self.metric!r}")
        if self.void_policy not in VOID_POLICIES:
            raise ValueError(f"void_policy must be one of {VOID_POLICIES}, got {self.void_policy!r}")
        if isinstance(self.weight_power, bool) or self.weight_power not in WEIGHT_POWERS:
            raise ValueError(f"weight_power must be one of {WEIGHT_POWERS}, got {self.weight_power!r}")


@dataclass
class IntegrationReport:
    stamp_ns: int
    seconds: float
    n_visible: int
    valid_pixels: int


@dataclass
class SemanticResult:
    """The quantized semantic map at one moment."""

    palette: Palette
    quantization: Quantization
    object_ids: np.ndarray  # (N,) uint32 packed palette color per Gaussian, UNOBSERVED_ID if unobserved
    confidence: np.ndarray  # (N,) float32 in [0, 1], 0 where unobserved
    observed: np.ndarray  # (N,) bool

    def object_rgb(self) -> np.ndarray:
        """(N, 3) uint8 palette color per Gaussian; unobserved Gaussians are grey."""
        rgb = np.full((len(self.object_ids), 3), 128, np.uint8)
        known = self.quantization.index >= 0
        rgb[known] = self.palette.colors[self.quantization.index[known]]
        return rgb


@dataclass
class MapUpdateReport:
    carried: int  # observed Gaussians whose evidence carried over to the new map
    dropped: int  # observed Gaussians whose evidence was dropped (removed, or moved beyond the tolerance)
    gaussians: int  # size of the new map
    by: str  # "ids" or "position"


def label_gaussians(state: SemanticState, palette: Palette, metric: str) -> SemanticResult:
    """Snaps every observed Gaussian's deblended color to the palette (METHOD section 4)."""
    q = quantize(state.colors(), palette.colors, metric=metric)
    known = q.index >= 0
    object_ids = np.full(len(state), UNOBSERVED_ID, np.uint32)
    object_ids[known] = palette.ids[q.index[known]]
    conf = np.where(known, confidence(q), 0.0).astype(np.float32)
    return SemanticResult(palette, q, object_ids, conf, state.observed.copy())


class SemanticMapper:
    def __init__(self, gaussians: GaussianMap, config: MapperConfig | None = None) -> None:
        self.config = config or MapperConfig()
        self.gaussians = gaussians
        self.state = SemanticState.zeros(len(gaussians), ids=gaussians.ids)
        self.palette_builder = PaletteBuilder()
        self.map_version = 0  # bumped on every map update, so snapshots can skip rewriting an unchanged map
        self._result: SemanticResult | None = None

    @property
    def n_keyframes(self) -> int:
        return len(self.state.stamps_ns)

    def integrate(self, keyframe: Keyframe) -> IntegrationReport:
        """Adds one keyframe's evidence. Raises DuplicateKeyframeError (state untouched) on a repeated stamp."""
        if self.state.has_stamp(keyframe.stamp_ns):
            raise DuplicateKeyframeError(f"keyframe stamp {keyframe.stamp_ns} was already integrated")
        start = time.perf_counter()
        valid = None
        if self.config.void_policy == "skip":
            valid = np.any(keyframe.mask != np.array(VOID_RGB, np.uint8), axis=2)
        evidence = accumulate(
            self.gaussians,
            keyframe.mask,
            keyframe.intrinsics,
            keyframe.cam_to_world,
            valid=valid,
            weight_power=self.config.weight_power,
            impl=self.config.impl,
            device=self.config.device,
        )
        # Only after the kernel succeeded: a failure above leaves state and palette as they were.
        self.palette_builder.update(keyframe.mask)
        self.state.add(evidence, keyframe.stamp_ns)
        self._result = None
        return IntegrationReport(
            stamp_ns=keyframe.stamp_ns,
            seconds=time.perf_counter() - start,
            n_visible=int(evidence.n_visible),
            valid_pixels=int(valid.sum()) if valid is not None else keyframe.mask.shape[0] * keyframe.mask.shape[1],
        )

    def result(self) -> SemanticResult:
        """Quantized labels for every Gaussian (cached until the next keyframe or map update)."""
        if self._result is None:
            self._result = label_gaussians(self.state, self.palette_builder.build(), self.config.metric)
        return self._result

    def update_gaussians(self, gaussians: GaussianMap) -> MapUpdateReport:
        """Swaps in a new map from the SLAM front-end, carrying accumulated evidence over.

        With stable ids on both maps, evidence follows the id (moved Gaussians keep theirs). Without,
        it follows position (mutual nearest neighbours within `reassociation_tolerance`).
        """
        old_observed = int(self.state.observed.sum())
        if gaussians.ids is not None and self.gaussians.ids is not None:
            state = self.state.reindexed_by_ids(gaussians.ids)
            by = "ids"
        else:
            tol = self.config.reassociation_tolerance
            state = reindex_by_position(self.state, self.gaussians.means, gaussians.means, tol, new_ids=gaussians.ids)
            by = "position"
        carried = int(state.observed.sum())
        self.gaussians = gaussians
        self.state = state
        self.map_version += 1
        self._result = None
        return MapUpdateReport(carried=carried, dropped=old_observed - carried, gaussians=len(gaussians), by=by)
