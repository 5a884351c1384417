"""The semantic mapper: keyframes in, per-Gaussian object labels out (no ROS).

One class integrates keyframes into the evidence of a Gaussian map: per keyframe either per-object votes
(`semantic_mode` "vote", the default: core.evidence.votes) or the paper's SCD color sums with palette
quantization ("scd": core.evidence.state, core.evidence.quantize), and the palette seen so far. A new map
from the SLAM front-end takes the evidence over (`take_map`) as core.follow.map_updater decides. The offline
`monovoc map` command and the live `semantic_mapper` node both wrap this class (through core.session), so a
bag processed offline and the same bag replayed through the node give the same semantic map.
"""

from __future__ import annotations

import math
import threading
import time
from concurrent.futures import CancelledError, Future
from dataclasses import dataclass, field

import numpy as np

from monovoc_ros.core.evidence.palette import UNOBSERVED_ID, VOID_ID, VOID_RGB, Palette, PaletteBuilder, unpack_rgb
from monovoc_ros.core.evidence.pixel_labels import mask_labels
from monovoc_ros.core.evidence.quantize import METRICS, Quantization, confidence, quantize
from monovoc_ros.core.evidence.state import GaussianEvidence, SemanticState
from monovoc_ros.core.evidence.votes import DEFAULT_SLOTS, VoteState, weakly_supported
from monovoc_ros.core.follow.keyframe_log import DEFAULT_MAX_BYTES, KeyframeLog, LoggedKeyframe
from monovoc_ros.core.follow.map_follow import FollowConfig
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.object_geometry import ObjectGeometry, object_geometry
from monovoc_ros.core.raster import IMPLEMENTATIONS, WEIGHT_POWERS, accumulate, accumulate_votes
from monovoc_ros.core.raster.constants import NEAR_PLANE
from monovoc_ros.core.segments.association import (
    MASK_ID_MODES,
    Association,
    AssociationConfig,
    Associator,
    associate_keyframe,
)
from monovoc_ros.core.segments.segment_labels import LabelHistogram

VOID_POLICIES = ("skip", "include")
SEMANTIC_MODES = ("vote", "scd")
# Per semantic mode, the MapperConfig fields that change what a keyframe adds to the evidence.
_EVIDENCE_SETTINGS = {
    "scd": ("semantic_mode", "weight_power", "void_policy"),
    "vote": ("semantic_mode", "weight_power", "void_policy", "vote_slots", "metric", "min_snap_margin",
             "object_colors", "mask_ids", "min_support"),
}  # fmt: skip


class DuplicateKeyframeError(ValueError):
    """A keyframe whose stamp was already integrated (its evidence would count twice)."""


@dataclass
class MapperConfig:
    impl: str = "numba"  # rasterizer implementation (core.raster.IMPLEMENTATIONS)
    device: str | None = None  # torch device when impl == "torch"
    metric: str = "cmc"  # palette quantization metric (core.evidence.quantize.METRICS)
    # Void (pure white) mask pixels: "skip" adds no evidence from them (they are "don't know", not an
    # object); "include" treats white like a color, pulling partly-void Gaussians toward white.
    void_policy: str = "skip"
    # Map updates: a new Gaussian without an old id takes the evidence of the nearest old Gaussian (moved
    # by the map's estimated motion) within this distance plus its own largest scale (metres; core.follow.map_follow).
    reassociation_tolerance: float = 0.03
    # Exponent k of the evidence weights w_ip^k (core.raster.WEIGHT_POWERS): 1 is the paper's SCD; 4 cut
    # the labelling errors at object boundaries most (README, "Choices").
    weight_power: int = 4
    # "vote": per-object weighted votes (METHOD section 8); "scd": the paper's color deblending + CMC.
    semantic_mode: str = "vote"
    # Objects kept per Gaussian in vote mode (the rest pooled as "other"; exact up to this many).
    vote_slots: int = DEFAULT_SLOTS
    # Vote mode: a pixel whose color is no palette color is snapped to the nearest one (with `metric`)
    # when the relative margin (d2 - d1) / (d2 + d1) of its two nearest palette colors is at least this.
    min_snap_margin: float = 0.5
    # Vote mode: the known object colors (packed 0xRRGGBB, e.g. from a labels file). Empty: each mask's
    # own region colors are its objects; given: every pixel is an exact color of these or snaps to one,
    # which is what lossy (JPEG) masks need, whose flat regions drift off the true colors.
    object_colors: tuple[int, ...] = ()
    # "global": a mask color names the same object in every keyframe; "per_frame": segment ids hold for
    # one mask only and are associated with the map's objects (core.segments.association; vote mode only).
    mask_ids: str = "global"
    # per_frame: overlaps are counted on the map rendered at 1/association_scale of the mask resolution.
    association_scale: int = 2
    # Bytes the keyframe log (core.follow.keyframe_log: masks, poses, segments for re-integration) may hold.
    keyframe_log_bytes: int = DEFAULT_MAX_BYTES
    # A map update that carries the evidence of less than this share of the labelled Gaussians, or that
    # bends the map (core.follow.map_motion: a field offset of core.follow.map_updater.REINTEGRATE_BEND_M or
    # more), is followed by a re-integration of the logged keyframes with their poses moved with the map;
    # 0: never.
    reintegrate_below: float = 0.9
    # Vote mode: a Gaussian keeps its object only where the object's share of its votes, void pixels counted
    # against it, is at least this fraction of the median share over the object's Gaussians (0 = off). A
    # segmenter leaves everything it does not detect void, so a mask that bleeds over an object's border
    # would otherwise grow the object by every Gaussian it ever touched; relative to the object's own
    # median, an object detected in few frames keeps its Gaussians (core.evidence.votes.weakly_supported).
    min_support: float = 0.0
    # Vote mode: objects whose segment names add up to less than this summed score are no objects (their
    # Gaussians unlabelled): the fragments a segmenter's unsure masks leave; one confident detection
    # (score >= this) is enough. Objects never named are kept. 0 = off.
    min_object_score: float = 0.0
    # Metres of camera depth beyond which Gaussians take no evidence from a keyframe (0 = no limit), as a depth
    # integrator's maximum range (nvblox's projective integrator: 7 m). In a building most of a view's frustum
    # lies behind walls: office_0 tiled to 1M Gaussians, 51% of the Gaussians in view are beyond 10 m and get
    # none of the weight, yet every one is projected, sorted, binned and reduced (core.raster). Not an evidence
    # setting: maps built with another range (snapshots of before it: none) resume and merge, as the range
    # only leaves far Gaussians without a keyframe's evidence.
    max_depth_m: float = 10.0

    def __post_init__(self) -> None:
        if self.impl not in IMPLEMENTATIONS:
            raise ValueError(f"impl must be one of {IMPLEMENTATIONS}, got {self.impl!r}")
        if self.metric not in METRICS:
            raise ValueError(f"metric must be one of {METRICS}, got {self.metric!r}")
        if self.void_policy not in VOID_POLICIES:
            raise ValueError(f"void_policy must be one of {VOID_POLICIES}, got {self.void_policy!r}")
        if isinstance(self.weight_power, bool) or self.weight_power not in WEIGHT_POWERS:
            raise ValueError(f"weight_power must be one of {WEIGHT_POWERS}, got {self.weight_power!r}")
        if self.semantic_mode not in SEMANTIC_MODES:
            raise ValueError(f"semantic_mode must be one of {SEMANTIC_MODES}, got {self.semantic_mode!r}")
        if isinstance(self.vote_slots, bool) or not isinstance(self.vote_slots, int) or not 1 <= self.vote_slots <= 16:
            raise ValueError(f"vote_slots must be an integer in [1, 16], got {self.vote_slots!r}")
        if not 0.0 <= float(self.min_snap_margin) <= 1.0:
            raise ValueError(f"min_snap_margin must be in [0, 1], got {self.min_snap_margin!r}")
        colors = tuple(sorted({int(c) for c in self.object_colors}))
        if any(not 0 <= c < VOID_ID for c in colors):
            raise ValueError("object_colors must be packed 24-bit colors other than void white")
        self.object_colors = colors
        if self.mask_ids not in MASK_ID_MODES:
            raise ValueError(f"mask_ids must be one of {MASK_ID_MODES}, got {self.mask_ids!r}")
        if self.mask_ids == "per_frame" and self.semantic_mode != "vote":
            raise ValueError("mask_ids 'per_frame' needs semantic_mode 'vote' (association merges per-object votes)")
        if self.semantic_mode != "vote" and (self.min_support > 0 or self.min_object_score > 0):
            raise ValueError("min_support and min_object_score need semantic_mode 'vote'")
        if not float(self.min_object_score) >= 0.0:
            raise ValueError(f"min_object_score must be >= 0, got {self.min_object_score!r}")
        if not 0.0 <= float(self.min_support) <= 1.0:
            raise ValueError(f"min_support must be in [0, 1], got {self.min_support!r}")
        if not (float(self.max_depth_m) == 0.0 or float(self.max_depth_m) > NEAR_PLANE):
            raise ValueError(f"max_depth_m must be 0 (no limit) or more than {NEAR_PLANE} m, got {self.max_depth_m!r}")
        if not 0.0 <= float(self.reintegrate_below) <= 1.0:
            raise ValueError(f"reintegrate_below must be in [0, 1], got {self.reintegrate_below!r}")
        if isinstance(self.keyframe_log_bytes, bool) or int(self.keyframe_log_bytes) < 0:
            raise ValueError(f"keyframe_log_bytes must be >= 0, got {self.keyframe_log_bytes!r}")
        if isinstance(self.association_scale, bool) or self.association_scale not in (1, 2, 3, 4):
            raise ValueError(f"association_scale must be 1, 2, 3 or 4, got {self.association_scale!r}")
        if self.mask_ids == "per_frame" and self.object_colors:
            raise ValueError("mask_ids 'per_frame' cannot take object_colors: per-frame mask colors name no object")

    @property
    def max_depth(self) -> float:
        """`max_depth_m` as the raster kernels take it: inf for no limit."""
        return float(self.max_depth_m) or math.inf

    def follow(self) -> FollowConfig:
        """How map updates carry evidence over (core.follow.map_follow)."""
        return FollowConfig(radius=self.reassociation_tolerance)

    def evidence_settings(self) -> dict:
        """The settings that shape accumulated evidence: maps whose evidence settings differ can be
        neither merged nor resumed into each other (the other settings may change freely)."""
        return {name: getattr(self, name) for name in _EVIDENCE_SETTINGS[self.semantic_mode]}

    def empty_state(self, n: int, ids: np.ndarray | None) -> GaussianEvidence:
        """The evidence store of this configuration's semantic mode for a map of n Gaussians."""
        if self.semantic_mode == "vote":
            return VoteState.zeros(n, self.vote_slots, ids)
        return SemanticState.zeros(n, ids)


@dataclass
class IntegrationReport:
    stamp_ns: int
    seconds: float
    n_visible: int
    valid_pixels: int
    snapped_pixels: int = 0  # vote mode: non-palette pixels snapped to a palette color
    ambiguous_pixels: int = 0  # vote mode: non-palette pixels left without evidence
    association: Association | None = None  # mask_ids per_frame: how the segments were associated
    keyframe: Keyframe | None = None  # the keyframe integrated (per_frame: its mask in object colors)


@dataclass
class SemanticResult:
    """The quantized semantic map at one moment."""

    palette: Palette
    object_ids: np.ndarray  # (N,) uint32 packed palette color per Gaussian, UNOBSERVED_ID if unobserved
    confidence: np.ndarray  # (N,) float32 in [0, 1] (vote margin, or quantization margin), 0 where unobserved
    observed: np.ndarray  # (N,) bool
    quantization: Quantization | None = None  # SCD mode only
    _objects: tuple[GaussianMap, ObjectGeometry] | None = field(default=None, init=False, repr=False, compare=False)
    _objects_lock: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False, compare=False)
    # The result this one follows (``follows``): its geometry, once computed, is where ours starts; or a Future of it
    # (a map update's seed), waited for by ``objects`` only.
    _before: SemanticResult | Future | None = field(default=None, init=False, repr=False, compare=False)
    objects_seconds: float | None = field(default=None, init=False, repr=False, compare=False)  # once computed

    def follows(self, previous: SemanticResult | Future | None) -> None:
        """Lets ``objects`` start from ``previous``'s geometry (the result of the keyframe before, or the labels a
        map update carried over: ``carried``, possibly a Future of it still being computed beside the mapper): only
        the objects whose Gaussians changed are computed again. A result whose geometry was never computed is
        skipped over, so no chain of results is kept alive."""
        if isinstance(previous, SemanticResult) and previous._objects is None:
            previous = previous._before
        self._before = previous

    def _settled_before(self) -> SemanticResult | None:
        """``_before``, a Future of it waited for: only here, so that labels and the cloud made of them never wait
        for a map update's seed (1M Gaussians: ~0.1-0.25 s on a busy node). A seed that failed is raised here, once;
        the geometry is then computed from scratch."""
        while isinstance(self._before, Future):
            try:
                settled = self._before.result()
            except CancelledError:
                settled = None
            except BaseException:
                self._before = None
                raise
            # Replaced only now: a result made meanwhile (`follows` on another thread) still inherits the Future.
            self._before = None
            self.follows(settled)
        return self._before

    def objects(self, gaussians: GaussianMap) -> ObjectGeometry:
        """The objects' geometry in ``gaussians``, the map this result labels (core.object_geometry.object_geometry).

        Computed once per result and shared by everything that reports objects (the objects topic and its
        markers on the worker thread, the object index and objects.db on theirs), so they agree. After the
        previous result's geometry of the same map (``follows``): 18 ms at 1M Gaussians after one keyframe
        of office_0; else (a map update) from scratch, 23 / 127 ms at 200k / 1M (bench_object_geometry.py)."""
        with self._objects_lock:
            if self._objects is None or self._objects[0] is not gaussians:
                start = time.perf_counter()
                settled = self._settled_before()
                before = settled._objects if settled is not None else None
                previous = before[1] if before is not None and before[0] is gaussians else None
                geometry = object_geometry(gaussians, self.object_ids, self.confidence, previous=previous)
                self.objects_seconds = time.perf_counter() - start
                self._objects, self._before = (gaussians, geometry), None
            return self._objects[1]

    def carried(self, sources: np.ndarray, gaussians: GaussianMap) -> SemanticResult:
        """The labels of a new map whose Gaussian j takes the evidence of this result's row sources[j] (-1: none),
        as a map update's transfer predicts them, with their geometry in `gaussians` computed. A map update
        computes it beside the mapper (core.follow.map_updater.update_map), and the first result after the update
        starts its geometry there (`SemanticMapper.take_map`): only the objects whose labels differ are computed
        again, instead of every object from scratch (1M Gaussians: ~130-250 ms on a live worker)."""
        taken = sources >= 0  # (M,) bool
        rows = sources[taken]
        ids = np.full(len(sources), UNOBSERVED_ID, np.uint32)
        conf = np.zeros(len(sources), np.float32)
        ids[taken], conf[taken] = self.object_ids[rows], self.confidence[rows]
        out = SemanticResult(self.palette, ids, conf, ids != UNOBSERVED_ID)
        out.objects(gaussians)
        return out

    def object_rgb(self) -> np.ndarray:
        """(N, 3) uint8 object color per Gaussian; unobserved Gaussians are grey."""
        rgb = np.full((len(self.object_ids), 3), 128, np.uint8)
        known = self.object_ids != UNOBSERVED_ID
        rgb[known] = unpack_rgb(self.object_ids[known])
        return rgb


def label_gaussians(state: SemanticState, palette: Palette, metric: str) -> SemanticResult:
    """Snaps every observed Gaussian's deblended color to the palette (METHOD section 4)."""
    q = quantize(state.colors(), palette.colors, metric=metric)
    known = q.index >= 0
    object_ids = np.full(len(state), UNOBSERVED_ID, np.uint32)
    object_ids[known] = palette.ids[q.index[known]]
    conf = np.where(known, confidence(q), 0.0).astype(np.float32)
    return SemanticResult(palette, object_ids, conf, state.observed.copy(), q)


def evidence_mismatch(a: MapperConfig, b: MapperConfig) -> tuple[str, object, object]:
    """The first evidence setting on which `a` and `b` differ and its two values, or ("", None, None)."""
    mine, theirs = a.evidence_settings(), b.evidence_settings()
    for name in dict.fromkeys([*mine, *theirs]):
        if mine.get(name) != theirs.get(name):
            return name, getattr(a, name), getattr(b, name)
    return "", None, None


class SemanticMapper:
    def __init__(self, gaussians: GaussianMap, config: MapperConfig | None = None) -> None:
        self.config = config or MapperConfig()
        self.gaussians = gaussians
        self.state: GaussianEvidence = self.config.empty_state(len(gaussians), gaussians.ids)
        self.palette_builder = PaletteBuilder()
        self.map_version = 0  # bumped on every map update, so snapshots can skip rewriting an unchanged map
        self._result: SemanticResult | None = None
        # The newest result and the map it labels: what the next result's geometry starts from (`labelling`).
        self._last_result: tuple[GaussianMap, SemanticResult] | None = None
        self._seed: Future | None = None  # a map update's SemanticResult.carried, being computed (take_map)
        # Vote mode keeps every Gaussian's label and confidence and re-labels only what a keyframe touched.
        self._labels: tuple[np.ndarray, np.ndarray] | None = None
        self._dirty: list[np.ndarray] = []  # rows touched since the labels were last brought up to date
        known = np.array(self.config.object_colors, np.uint32)
        self._known_palette = Palette.from_colors(unpack_rgb(known)) if known.size else None
        self.associator: Associator | None = None
        if self.config.mask_ids == "per_frame":
            self.associator = Associator(AssociationConfig(render_scale=self.config.association_scale))
        self.segment_labels = LabelHistogram()  # per object, the class names its segments were given
        self.keyframe_log = KeyframeLog(self.config.keyframe_log_bytes)  # what re-integration replays

    @property
    def n_keyframes(self) -> int:
        return len(self.state.stamps_ns)

    def integrate(self, keyframe: Keyframe, logged: LoggedKeyframe | None = None) -> IntegrationReport:
        """Adds one keyframe's evidence. Raises DuplicateKeyframeError (state untouched) on a repeated stamp.
        `logged`: the keyframe's log entry when it comes from a log (re-integration), kept as it is."""
        if self.state.has_stamp(keyframe.stamp_ns):
            raise DuplicateKeyframeError(f"keyframe stamp {keyframe.stamp_ns} was already integrated")
        start = time.perf_counter()
        given, association = keyframe, None
        if self.associator is not None:
            keyframe, association = self._associate(keyframe)
        if self.config.semantic_mode == "vote":
            report = self._integrate_votes(keyframe)
        else:
            report = self._integrate_scd(keyframe)
        report.association, report.keyframe = association, keyframe
        if keyframe.segments:  # a segment's id is now its object's id
            self.segment_labels.add_keyframe(keyframe.segments, {s.id: s.id for s in keyframe.segments})
        if logged is None:
            self.keyframe_log.add(given)
        else:
            self.keyframe_log.append(logged)
        self._result = None
        report.seconds = time.perf_counter() - start
        return report

    def _associate(self, keyframe: Keyframe) -> tuple[Keyframe, Association]:
        """Per-frame mask ids: the keyframe with its segments in the colors of the objects they were
        associated with (core.segments.association), after merging the objects the association found to be one."""
        ids, conf = self._vote_labels()
        keyframe, association = associate_keyframe(
            self.associator, self.gaussians, ids, keyframe,
            metric=self.config.metric, min_snap_margin=self.config.min_snap_margin, runner_up_ids=self.state.runner_up,
            object_names=self.segment_labels.scores,
        )  # fmt: skip
        for keep, drop in association.merges:
            rows = self.state.merge_objects(keep, drop)
            self.state.relabel(rows, ids, conf)
            self.palette_builder.merge_ids(keep, drop)
            self.segment_labels.merge_objects(keep, drop)
        return keyframe, association

    def _vote_labels(self) -> tuple[np.ndarray, np.ndarray]:
        """Every Gaussian's current object id and confidence (vote mode), kept between calls."""
        if self._labels is None:
            self._labels, self._dirty = self.state.labels(), []
        if self._dirty:  # only what the keyframes since the last call touched can have changed
            touched = np.zeros(len(self.state), bool)
            for rows in self._dirty:
                touched[rows] = True
            self.state.relabel(np.flatnonzero(touched), *self._labels)
            self._dirty = []
        return self._labels

    def _integrate_scd(self, keyframe: Keyframe) -> IntegrationReport:
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
            max_depth=self.config.max_depth,
            impl=self.config.impl,
            device=self.config.device,
        )
        # Only after the kernel succeeded: a failure above leaves state and palette as they were.
        self.palette_builder.update(keyframe.mask)
        self.state.add(evidence, keyframe.stamp_ns)
        h, w = keyframe.mask.shape[:2]
        return IntegrationReport(
            keyframe.stamp_ns, 0.0, int(evidence.n_visible), int(valid.sum()) if valid is not None else h * w
        )

    def _integrate_votes(self, keyframe: Keyframe) -> IntegrationReport:
        labelled, own = mask_labels(
            keyframe.mask,
            self.config.metric,
            self.config.min_snap_margin,
            # Void votes count against objects when they decide support (min_support) too.
            include_void=self.config.void_policy == "include" or self.config.min_support > 0,
            palette=self._known_palette,
        )
        labels = labelled.labels
        votes = accumulate_votes(
            self.gaussians,
            labels,
            keyframe.intrinsics,
            keyframe.cam_to_world,
            weight_power=self.config.weight_power,
            max_depth=self.config.max_depth,
            impl=self.config.impl,
            device=self.config.device,
        )
        named = votes.labels >= 0
        objects = np.append(labelled.objects, np.uint32(0))[votes.labels]  # label -1 -> 0, an unused entry
        # Void votes (void_policy include) name no object: they count against every object's margin.
        void = named & (objects == VOID_ID)
        if void.any():
            pooled = votes.other + np.where(void, votes.weights, 0.0).sum(axis=1)
            named &= ~void
        else:  # the (V, E) row sum is a tenth of the re-integration budget and adds zeros here
            pooled = votes.other
        weights = np.where(named, votes.weights, 0.0)
        self.state.add(votes.rows, objects, weights, pooled, keyframe.stamp_ns)
        self.palette_builder.absorb(own)
        if self._labels is not None:
            self._dirty.append(votes.rows)
        return IntegrationReport(
            keyframe.stamp_ns,
            0.0,
            int(votes.n_visible),
            int((labels >= 0).sum()),
            labelled.snapped_pixels,
            labelled.ambiguous_pixels,
        )

    def object_labels(self) -> dict[int, str]:
        """Object id -> the leading class name its segments were given (core.segments.segment_labels)."""
        return self.segment_labels.leading()

    def object_label_confidence(self) -> dict[int, float]:
        """Object id -> the share of its segments' class evidence that names its label (`object_labels`)."""
        return self.segment_labels.leading_share()

    def result(self) -> SemanticResult:
        """Labels for every Gaussian (cached until the next keyframe or map update)."""
        if self._result is None:
            previous = self._previous_result()
            palette = self.palette_builder.build()
            if self.config.semantic_mode == "scd":
                self._result = label_gaussians(self.state, palette, self.config.metric)
            else:
                ids, conf = (a.copy() for a in self._vote_labels())
                if self.config.min_support > 0:
                    weak = weakly_supported(ids, self.state.support(), self.config.min_support)
                    ids[weak], conf[weak] = UNOBSERVED_ID, 0.0
                if self.config.min_object_score > 0:
                    fragments = self.segment_labels.weakly_named(self.config.min_object_score)
                    dropped = np.isin(ids, np.asarray(fragments, np.uint32))
                    ids[dropped], conf[dropped] = UNOBSERVED_ID, 0.0
                self._result = SemanticResult(palette, ids, conf, ids != UNOBSERVED_ID)
            self._result.follows(previous)
            self._last_result = (self.gaussians, self._result)
        return self._result

    def _previous_result(self) -> SemanticResult | Future | None:
        """Where the next result's geometry starts: the newest result, or after a map update its seed (a Future,
        computed beside the update's end and the next keyframe: `SemanticResult.objects` waits for it)."""
        if self._seed is None:
            return self._last_result[1] if self._last_result is not None else None
        seed, self._seed = self._seed, None
        return seed

    def labelling(self) -> tuple[GaussianMap, SemanticResult] | None:
        """The newest result and the map it labels, None before the first `result` of this map: read in one
        step, so a thread planning a map update may ask (core.follow.map_updater)."""
        return self._last_result

    def merged(self, other: SemanticMapper) -> SemanticMapper:
        """A mapper holding both mappers' evidence and palette counts: two robots or two bags of the
        same Gaussian map. The evidence settings must agree and no keyframe may be in both."""
        if self.associator is not None or other.associator is not None:
            raise ValueError("cannot merge maps built with per-frame mask ids (their object ids are their own)")
        name, mine, theirs = evidence_mismatch(self.config, other.config)
        if name:
            raise ValueError(f"cannot merge maps built with different {name} ({mine!r} vs {theirs!r})")
        if len(self.gaussians) != len(other.gaussians) or not (
            np.array_equal(self.gaussians.ids, other.gaussians.ids)
            if self.gaussians.ids is not None and other.gaussians.ids is not None
            else np.array_equal(self.gaussians.means, other.gaussians.means)
        ):
            raise ValueError("cannot merge maps of different Gaussian maps (same ids, or same means without ids)")
        out = SemanticMapper(self.gaussians, self.config)
        out.state = self.state.merged(other.state)
        out.palette_builder = self.palette_builder.merged(other.palette_builder)
        out.segment_labels = self.segment_labels.merged(other.segment_labels)
        out.map_version = max(self.map_version, other.map_version)
        return out

    def take_map(self, gaussians: GaussianMap, sources: np.ndarray, seed: Future | None = None) -> tuple[int, int]:
        """Swaps in a new map from the SLAM front-end whose Gaussian j takes the evidence of this map's row
        sources[j] (-1: none; core.follow.map_updater decides them). Returns (observed old Gaussians whose
        evidence went to at least one new Gaussian, observed old Gaussians). `seed`: a Future of this map's
        labels as carried to `gaussians` (SemanticResult.carried), where the next result's geometry starts."""
        old_observed = self.state.observed
        hit = sources >= 0
        labels = None
        if self._labels is not None:  # vote mode: a row's label is its evidence's, and the rows are carried whole
            ids, confidence = self._vote_labels()
            take = np.maximum(sources, 0)
            # A gather where labelling the new map took ~25 ms at 1M, in the first publication after each update.
            labels = (
                np.where(hit, ids[take], UNOBSERVED_ID).astype(np.uint32, copy=False),
                np.where(hit, confidence[take], np.float32(0.0)).astype(np.float32, copy=False),
            )
        state = self.state.carried_over(sources, gaussians.ids)
        used = np.zeros(len(old_observed), bool)
        used[sources[hit]] = True
        carried = int(np.count_nonzero(used & old_observed))
        self.gaussians = gaussians
        self.state = state
        self.map_version += 1
        self._result = self._last_result = None
        self._seed = seed
        self._labels, self._dirty = labels, []
        return carried, int(np.count_nonzero(old_observed))

    def rename_objects(self, mapping: dict[int, int]) -> None:
        """Vote mode: object ids renamed (old id -> new id, one to one; others stay) in the evidence, the
        palette counts and the segment labels (a rebuilt map taking the ids its predecessor's users know:
        core.follow.map_updater.keep_object_ids, which renames the associator's ids itself)."""
        if not isinstance(self.state, VoteState):
            raise ValueError("rename_objects needs semantic_mode 'vote'")
        self.state.rename_objects(mapping)
        self.palette_builder.rename_ids(mapping)
        self.segment_labels.rename_objects(mapping)
        self._result = None
        self._labels, self._dirty = None, []

    def rebuilt(self) -> SemanticMapper:
        """A mapper of the same map and configuration whose evidence is the logged keyframes integrated
        again, with their current poses (what a re-integration swaps in when done)."""
        out = SemanticMapper(self.gaussians, self.config)
        out.map_version = self.map_version
        return out
