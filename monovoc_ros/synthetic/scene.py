"""The synthetic Replica-like sequence: configuration, generation, and lazy keyframe rendering.

Masks, depth and RGB are ray cast from the analytic surfaces, never from the Gaussians, so the map and
the segmentations are two independent views of one scene, as with a real SLAM map and a real segmenter.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field, fields

import numpy as np

from monovoc_ros.core.evaluation.datasets import Sequence
from monovoc_ros.core.keyframe import Keyframe
from monovoc_ros.core.map.camera import Intrinsics
from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.synthetic import corruption
from monovoc_ros.synthetic.appearance import Appearance
from monovoc_ros.synthetic.errors import SyntheticError
from monovoc_ros.synthetic.layout import ROOM_MAX, ROOM_MIN, SurfaceSpec, room_layout
from monovoc_ros.synthetic.palette import VOID_RGB, distinct_palette, make_confusable
from monovoc_ros.synthetic.primitives import Primitive, pack
from monovoc_ros.synthetic.raycast import bounding_spheres, camera_rays, cast_rays
from monovoc_ros.synthetic.sampling import sample_map
from monovoc_ros.synthetic.trajectory import camera_loop
from monovoc_ros.synthetic.visibility import observed_views, typical_pixel_size

VARIANTS = ("clean", "confusable", "boundary_noise", "label_noise", "mixed_boundary", "region_artifacts")
FLOATER = -1  # gaussian_object of a Gaussian in free space
UNLABELLED = -2  # gaussian_object of a Gaussian on a surface the segmentation leaves void (window, vent)
_RENDER_CACHE = 6  # keyframes whose ray cast is kept (mask, depth and RGB of one view share it)


@dataclass
class SceneConfig:
    seed: int = 0
    n_gaussians: int = 140_000
    n_keyframes: int = 60
    width: int = 616
    height: int = 344
    fx: float = 308.0
    fy: float = 303.53
    cx: float = 307.74
    cy: float = 171.75
    variant: str = "clean"
    floater_fraction: float = 0.005
    surface_noise: float = 0.001  # std (m) of Gaussian centres along the surface normal
    tangent_scale_range: tuple[float, float] = (0.01, 0.03)  # tangent sigmas (m) away from edges are clipped to this
    min_tangent_scale: float = 0.0025  # smallest tangent sigma (m) of the Gaussians that edges shrink
    edge_adaptive: bool = True  # shrink Gaussians across face edges and densify there, as optimisation does
    observed_only: bool = True  # Gaussians only on surface points some keyframe sees, as a SLAM map has
    low_opacity_fraction: float = 0.1  # surface Gaussians with opacity 0.05-0.5 instead of 0.6-0.99
    confusable_pairs: int = 3  # confusable: pairs of objects given near-identical colors
    confusable_delta: int = 6  # confusable: max-norm RGB distance within a pair
    boundary_width: int = 2  # boundary_noise: pixels this close to another label may swap
    boundary_swap_prob: float = 0.5  # boundary_noise: probability that such a pixel swaps
    label_noise_fraction: float = 0.1  # label_noise: fraction of pixels given a wrong palette color
    mixed_width: int = 1  # mixed_boundary: blend pixels this close to another label
    mixed_prob: float = 1.0  # mixed_boundary: probability that such a pixel is blended
    artifact_count: int = 12  # region_artifacts: blobs/lines per keyframe
    frame_rate: float = 10.0  # keyframe stamps: start_ns + k / frame_rate seconds
    start_ns: int = 0
    camera_phase: float = 0.0  # radians along the camera loop where keyframe 0 sits

    def __post_init__(self) -> None:
        self.validate()

    @classmethod
    def at_resolution(cls, width: int, height: int, **kwargs) -> SceneConfig:
        """The default (HI-SLAM2 Replica) camera resampled to ``width`` x ``height``; other fields as given."""
        k = cls.default_intrinsics().scaled_to(width, height)
        return cls(width=width, height=height, fx=k.fx, fy=k.fy, cx=k.cx, cy=k.cy, **kwargs)

    @staticmethod
    def default_intrinsics() -> Intrinsics:
        d = {f.name: f.default for f in fields(SceneConfig) if f.name in ("fx", "fy", "cx", "cy", "width", "height")}
        return Intrinsics(**d)

    def validate(self) -> None:
        def need(ok: bool, what: str) -> None:
            if not ok:
                raise SyntheticError(f"SceneConfig: {what}")

        need(self.variant in VARIANTS, f"variant must be one of {VARIANTS}, got {self.variant!r}")
        need(int(self.n_gaussians) >= 100, f"n_gaussians must be >= 100, got {self.n_gaussians}")
        need(int(self.n_keyframes) >= 1, f"n_keyframes must be >= 1, got {self.n_keyframes}")
        need(0.0 <= self.floater_fraction < 0.5, f"floater_fraction must be in [0, 0.5), got {self.floater_fraction}")
        need(self.surface_noise >= 0, f"surface_noise must be >= 0, got {self.surface_noise}")
        lo, hi = self.tangent_scale_range
        need(0 < lo <= hi, f"tangent_scale_range must be 0 < lo <= hi, got {self.tangent_scale_range}")
        # Above the largest normal sigma (2 mm), so the thin axis of every surface Gaussian stays its normal.
        need(
            0.002 < self.min_tangent_scale <= lo,
            f"min_tangent_scale must be in (0.002, {lo}], got {self.min_tangent_scale}",
        )
        need(0.0 <= self.low_opacity_fraction <= 1.0, "low_opacity_fraction must be in [0, 1]")
        need(self.confusable_pairs >= 1, f"confusable_pairs must be >= 1, got {self.confusable_pairs}")
        need(1 <= self.confusable_delta <= 60, f"confusable_delta must be in 1..60, got {self.confusable_delta}")
        need(self.boundary_width >= 1 and self.mixed_width >= 1, "boundary_width and mixed_width must be >= 1")
        for name in ("boundary_swap_prob", "label_noise_fraction", "mixed_prob"):
            need(0.0 <= getattr(self, name) <= 1.0, f"{name} must be in [0, 1], got {getattr(self, name)}")
        need(self.artifact_count >= 0, f"artifact_count must be >= 0, got {self.artifact_count}")
        need(self.frame_rate > 0, f"frame_rate must be > 0, got {self.frame_rate}")
        try:
            Intrinsics(self.fx, self.fy, self.cx, self.cy, self.width, self.height)
        except ValueError as exc:
            raise SyntheticError(f"SceneConfig: {exc}") from None

    @property
    def intrinsics(self) -> Intrinsics:
        return Intrinsics(self.fx, self.fy, self.cx, self.cy, self.width, self.height)


@dataclass(eq=False)
class SceneObject:
    """A labelled instance (or, in ``SyntheticScene.void_surfaces``, an unlabelled surface)."""

    instance_id: int
    class_name: str
    class_id: int
    palette_rgb: np.ndarray  # (3,) uint8; white for void surfaces
    primitives: tuple[int, ...]  # indices into SyntheticScene.primitives
    bbox_min: np.ndarray = field(repr=False)  # (3,) world-frame axis-aligned bounds of the analytic solid
    bbox_max: np.ndarray = field(repr=False)

    @property
    def centroid(self) -> np.ndarray:
        return (self.bbox_min + self.bbox_max) / 2


@dataclass(frozen=True)
class ViewRender:
    label: np.ndarray  # (H, W) int32 object index, -1 void
    prim: np.ndarray  # (H, W) int32 primitive index, -1 no hit
    depth: np.ndarray  # (H, W) float32 z-depth (m), inf no hit
    normals: np.ndarray  # (H, W, 3) float32


class SyntheticScene(Sequence):
    """A generated sequence; build it with ``generate_scene``. Keyframes render lazily on request."""

    def __init__(
        self,
        config: SceneConfig,
        surfaces: list[SurfaceSpec],
        palette: np.ndarray,
        gaussians: GaussianMap,
        gaussian_primitive: np.ndarray,
        appearance: Appearance,
        confusable_pairs: list[tuple[int, int]],
        poses: np.ndarray | None = None,
    ) -> None:
        self.config = config
        self.name = f"synthetic-{config.variant}-seed{config.seed}"
        self.intrinsics = config.intrinsics
        self.primitives: list[Primitive] = [prim for s in surfaces for prim, _ in s.parts]
        self.appearance = appearance
        self.confusable_pairs = confusable_pairs  # (object index, object index) pairs of the confusable variant

        self.objects: list[SceneObject] = []
        self.void_surfaces: list[SceneObject] = []
        surface_code = np.empty(len(self.primitives), np.int32)  # object index, or UNLABELLED
        start = 0
        for s in surfaces:
            idx = tuple(range(start, start + len(s.parts)))
            start += len(s.parts)
            lo = np.min([self.primitives[k].bounds()[0] for k in idx], axis=0)
            hi = np.max([self.primitives[k].bounds()[1] for k in idx], axis=0)
            if s.labelled:
                color = palette[len(self.objects)]
                self.objects.append(SceneObject(s.instance_id, s.class_name, s.class_id, color, idx, lo, hi))
                surface_code[list(idx)] = len(self.objects) - 1
            else:
                self.void_surfaces.append(
                    SceneObject(s.instance_id, s.class_name, s.class_id, VOID_RGB.copy(), idx, lo, hi)
                )
                surface_code[list(idx)] = UNLABELLED
        self.primitive_object = surface_code  # (P,) object index per primitive, UNLABELLED for void surfaces
        self._kinds, self._params = pack(self.primitives)
        self._spheres = bounding_spheres(self._kinds, self._params)
        # Color lookup by label + 1: void first.
        self.lut = np.concatenate([VOID_RGB[None], np.stack([o.palette_rgb for o in self.objects])]).astype(np.uint8)

        self.gaussians = gaussians
        self.gaussian_primitive = gaussian_primitive  # (N,) primitive index, -1 for floaters
        on_surface = gaussian_primitive >= 0
        self.gaussian_object = np.where(on_surface, surface_code[np.maximum(gaussian_primitive, 0)], FLOATER)
        self.gaussian_object = self.gaussian_object.astype(np.int32)
        self.gaussian_object.setflags(write=False)

        self.poses = camera_loop(config.n_keyframes, config.camera_phase) if poses is None else np.array(poses)
        self.poses.setflags(write=False)
        seconds = np.arange(config.n_keyframes) / config.frame_rate
        self.stamps_ns = config.start_ns + np.round(seconds * 1e9).astype(np.int64)
        self._cache: OrderedDict[int, ViewRender] = OrderedDict()

    # ------------------------------------------------------------------ geometry queries

    def cast(self, cam_to_world: np.ndarray, intrinsics: Intrinsics | None = None) -> ViewRender:
        """Ray casts any view: object labels (-1 void), primitive index, z-depth and normals per pixel."""
        k = intrinsics or self.intrinsics
        origin, dirs = camera_rays(cam_to_world, k)
        t, prim, normals = cast_rays(origin, dirs, self._kinds, self._params, self._spheres)
        code = np.where(prim >= 0, self.primitive_object[np.maximum(prim, 0)], -1)
        label = np.where(code >= 0, code, -1).astype(np.int32)
        h, w = k.height, k.width
        arrays = (label.reshape(h, w), prim.reshape(h, w), t.reshape(h, w).astype(np.float32),
                  normals.reshape(h, w, 3).astype(np.float32))  # fmt: skip
        for a in arrays:  # cached and shared between callers
            a.setflags(write=False)
        return ViewRender(*arrays)

    def _render(self, i: int) -> ViewRender:
        i = self._index(i)
        if i in self._cache:
            self._cache.move_to_end(i)
            return self._cache[i]
        r = self.cast(self.poses[i])
        self._cache[i] = r
        while len(self._cache) > _RENDER_CACHE:
            self._cache.popitem(last=False)
        return r

    def sdf(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (m) to the nearest surface of the scene; negative inside a solid or outside the room."""
        return np.min([p.sdf(points) for p in self.primitives], axis=0)

    def surface_distance(self, points: np.ndarray, object_index: int) -> np.ndarray:
        """Unsigned distance (m) of each point to the nearest surface of ``objects[object_index]``'s primitives."""
        prims = self.objects[object_index].primitives
        return np.min([np.abs(self.primitives[k].sdf(points)) for k in prims], axis=0)

    def gaussian_palette_rgb(self) -> np.ndarray:
        """(N, 3) uint8 ground-truth mask color of each Gaussian's surface; white for floaters and void surfaces."""
        return self.lut[np.maximum(self.gaussian_object, -1) + 1]

    # ------------------------------------------------------------------ per keyframe images

    def object_index_map(self, i: int) -> np.ndarray:
        """(H, W) int32 index into ``objects`` of the surface seen at each pixel; -1 for void."""
        return self._render(i).label

    def depth(self, i: int) -> np.ndarray:
        """(H, W) float32 z-depth in metres along the optical axis (the room is closed: always finite)."""
        return self._render(i).depth

    def rgb(self, i: int) -> np.ndarray:
        """(H, W, 3) uint8 shaded, textured image of keyframe ``i``."""
        r = self._render(i)
        i = self._index(i)
        origin, dirs = camera_rays(self.poses[i], self.intrinsics)
        points = origin + dirs * r.depth.reshape(-1, 1).astype(np.float64)
        prim = r.prim.ravel()
        col = self.appearance.color(prim, points, r.normals.reshape(-1, 3))
        return np.round(col * 255).astype(np.uint8).reshape(r.prim.shape + (3,))

    def clean_mask(self, i: int) -> np.ndarray:
        """(H, W, 3) uint8 ground-truth mask: one palette color per pixel, white = void."""
        return self.lut[self.object_index_map(i) + 1]

    def mask(self, i: int) -> np.ndarray:
        """The mask of keyframe ``i`` with the configured variant's corruption applied."""
        c, variant = self.config, self.config.variant
        labels = self.object_index_map(i)
        rng = np.random.default_rng([c.seed, 7919, VARIANTS.index(variant), self._index(i)])
        if variant in ("clean", "confusable"):
            return self.lut[labels + 1]
        if variant == "boundary_noise":
            labels = corruption.boundary_noise(labels, c.boundary_width, c.boundary_swap_prob, rng)
        elif variant == "label_noise":
            labels = corruption.label_noise(labels, c.label_noise_fraction, len(self.objects), rng)
        elif variant == "region_artifacts":
            labels = corruption.region_artifacts(labels, c.artifact_count, len(self.objects), rng)
        else:
            return corruption.mixed_boundary(labels, self.lut, c.mixed_width, c.mixed_prob, rng)
        return self.lut[labels + 1]

    def keyframe(self, i: int) -> Keyframe:
        i = self._index(i)
        return Keyframe(i, int(self.stamps_ns[i]), self.poses[i].copy(), self.intrinsics, self.mask(i), self.rgb(i))

    # ------------------------------------------------------------------ Sequence

    def load_gaussians(self) -> GaussianMap:
        return self.gaussians

    def labels(self) -> list[dict]:
        """One entry per labelled object, in the shape of Replica's labels.json."""
        return [
            {"color": [int(v) for v in o.palette_rgb], "instance_id": o.instance_id, "class_id": o.class_id,
             "class_name": o.class_name}
            for o in self.objects
        ]  # fmt: skip


def generate_scene(config: SceneConfig | None = None) -> SyntheticScene:
    """Builds the room, its palette, its Gaussian map and its camera loop; deterministic in ``config.seed``."""
    config = config or SceneConfig()
    config.validate()

    # One stream per stage, so that every variant of a seed shares its palette, map and textures.
    def stream(stage: int) -> np.random.Generator:
        return np.random.default_rng([config.seed, stage])

    surfaces = room_layout()
    n_objects = sum(s.labelled for s in surfaces)
    palette = distinct_palette(n_objects, stream(1))
    pairs: list[tuple[int, int]] = []
    if config.variant == "confusable":
        palette, pairs = make_confusable(palette, config.confusable_pairs, config.confusable_delta, stream(2))
    materials = [mat for s in surfaces for _, mat in s.parts]
    primitives = [prim for s in surfaces for prim, _ in s.parts]
    appearance = Appearance(materials, stream(3))
    rng = stream(4)

    # The trajectory comes first: a SLAM system creates Gaussians only where its keyframes saw a surface.
    poses = camera_loop(config.n_keyframes, config.camera_phase)
    observe = None
    if config.observed_only:
        kinds, params = pack(primitives)
        spheres = bounding_spheres(kinds, params)
        intrinsics = config.intrinsics

        def observe(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
            views, _ = observed_views(points, normals, poses, intrinsics, kinds, params, spheres, need=1)
            return views >= 1

    n_floaters = round(config.floater_fraction * config.n_gaussians)
    m = sample_map(
        primitives, appearance, config.n_gaussians - n_floaters, n_floaters, ROOM_MIN, ROOM_MAX, rng,
        surface_noise=config.surface_noise, tangent_scale_range=tuple(config.tangent_scale_range),
        low_opacity_fraction=config.low_opacity_fraction, min_tangent_scale=config.min_tangent_scale,
        edge_adaptive=config.edge_adaptive, observe=observe,
        pixel_size=typical_pixel_size(primitives, poses, config.intrinsics),
    )  # fmt: skip
    # A front-end's storage order has nothing to do with objects; ids grow with creation and have gaps
    # where Gaussians were pruned.
    n = config.n_gaussians
    order = rng.permutation(n)
    ids = np.sort(rng.choice(4 * n, n, replace=False)).astype(np.int64)
    gaussians = GaussianMap(
        means=m.means[order], scales=m.scales[order], quats=m.quats[order], opacities=m.opacities[order],
        colors=m.colors[order], ids=ids,
    )  # fmt: skip
    return SyntheticScene(config, surfaces, palette, gaussians, m.primitive[order], appearance, pairs, poses)
