"""A Gaussian map of the room as a SLAM front-end would leave it.

Flat Gaussians on the visible outer surfaces (jittered-grid positions, two tangent scales of ~0.6 grid
spacing, a 1-2 mm normal scale, a random in-plane orientation, a little position noise along the normal),
noisy opacities, colors from the same appearance model as the images, and a few floaters in free space.
Surface samples that lie inside or against another solid (a leg's foot on the rug, a sofa's back against
the wall, a pole inside a lamp shade) are dropped: reconstruction never sees those faces.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from monovoc_ros.core.synthetic.appearance import Appearance
from monovoc_ros.core.synthetic.primitives import Primitive, RoomFace, SurfaceSamples

CONTACT_EPS = 0.003  # samples closer than this to another solid are hidden against it
GRID_JITTER = 0.5  # fraction of a grid cell a sample may move: uniform-looking, yet no large gaps
FLOATER_CLEARANCE = 0.10  # floaters keep this far from every surface, so they are unambiguous
TANGENT_SCALE_PER_SPACING = 0.8  # sigma of a splat in grid spacings: neighbours overlap, no holes


@dataclass(frozen=True)
class SampledMap:
    means: np.ndarray  # (N, 3)
    scales: np.ndarray  # (N, 3)
    quats: np.ndarray  # (N, 4) wxyz
    opacities: np.ndarray  # (N,)
    colors: np.ndarray  # (N, 3)
    primitive: np.ndarray  # (N,) int32 primitive index, -1 for floaters
    spacing: float  # grid spacing reached (metres)


def _bounding_sphere(p: Primitive) -> tuple[np.ndarray, float]:
    lo, hi = p.bounds()
    return (lo + hi) / 2, float(np.linalg.norm(hi - lo) / 2)


def visible_surface_samples(primitives: list[Primitive], spacing: float, rng: np.random.Generator):
    """Jittered samples of every primitive's surface minus those inside or against another solid.

    Returns (SurfaceSamples, primitive index per sample).
    """
    spheres = [_bounding_sphere(p) for p in primitives]
    parts, owner = [], []
    for k, prim in enumerate(primitives):
        s = prim.sample(spacing, GRID_JITTER, rng)
        keep = np.ones(len(s.points), bool)
        ck, rk = spheres[k]
        for q, other in enumerate(primitives):
            cq, rq = spheres[q]
            if q == k or (not isinstance(other, RoomFace) and np.linalg.norm(ck - cq) > rk + rq + CONTACT_EPS):
                continue
            keep &= other.sdf(s.points) >= CONTACT_EPS
        parts.append(SurfaceSamples(s.points[keep], s.normals[keep], s.tangents[keep]))
        owner.append(np.full(int(keep.sum()), k, np.int32))
    return SurfaceSamples.concat(parts), np.concatenate(owner)


def _surface_samples_exact(primitives, n: int, rng: np.random.Generator):
    """Exactly ``n`` visible samples: refine the spacing until at least ``n`` survive, drop the excess."""
    area = sum(p.area() for p in primitives)
    spacing = float(np.sqrt(area / n))
    for _ in range(6):
        samples, owner = visible_surface_samples(primitives, spacing, rng)
        if len(owner) >= n:
            keep = np.sort(rng.choice(len(owner), n, replace=False))
            return (
                SurfaceSamples(samples.points[keep], samples.normals[keep], samples.tangents[keep]),
                owner[keep],
                spacing,
            )
        spacing *= float(np.sqrt(len(owner) / n)) * 0.99
    raise RuntimeError(f"could not place {n} surface samples")  # pragma: no cover - converges in 1-2 passes


def _floaters(primitives, n: int, room_min, room_max, rng: np.random.Generator) -> np.ndarray:
    out = np.zeros((0, 3))
    while len(out) < n:
        cand = rng.uniform(room_min, room_max, size=(max(64, 4 * n), 3))
        clear = np.min([p.sdf(cand) for p in primitives], axis=0) >= FLOATER_CLEARANCE
        out = np.concatenate([out, cand[clear]])
    return out[:n]


def sample_map(
    primitives: list[Primitive],
    appearance: Appearance,
    n_surface: int,
    n_floaters: int,
    room_min: np.ndarray,
    room_max: np.ndarray,
    rng: np.random.Generator,
    *,
    surface_noise: float = 0.001,
    tangent_scale_range: tuple[float, float] = (0.01, 0.03),
    low_opacity_fraction: float = 0.1,
) -> SampledMap:
    samples, prim, spacing = _surface_samples_exact(primitives, n_surface, rng)
    n = len(prim)
    normals = samples.normals / np.linalg.norm(samples.normals, axis=1, keepdims=True)
    t1 = samples.tangents - np.sum(samples.tangents * normals, axis=1, keepdims=True) * normals
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    psi = rng.uniform(0, np.pi, n)[:, None]  # orientation of the splat's long axis within the surface
    a1 = np.cos(psi) * t1 + np.sin(psi) * t2
    a2 = np.cross(normals, a1)
    frames = np.stack([a1, a2, normals], axis=2)  # columns: tangent, tangent, normal

    lo, hi = tangent_scale_range
    sigma = np.clip(TANGENT_SCALE_PER_SPACING * spacing, lo, hi)
    scales = np.stack(
        [
            np.clip(sigma * rng.uniform(0.8, 1.25, n), lo, hi),
            np.clip(sigma * rng.uniform(0.8, 1.25, n), lo, hi),
            rng.uniform(0.001, 0.002, n),
        ],
        axis=1,
    )
    opac = rng.uniform(0.6, 0.99, n)
    low = rng.random(n) < low_opacity_fraction
    opac[low] = rng.uniform(0.05, 0.5, int(low.sum()))
    colors = appearance.color(prim, samples.points, normals)
    means = samples.points + normals * rng.normal(0.0, surface_noise, (n, 1)) if surface_noise > 0 else samples.points

    fl = _floaters(primitives, n_floaters, room_min, room_max, rng)
    m = len(fl)
    xyzw = Rotation.from_matrix(frames).as_quat()
    fl_xyzw = Rotation.random(m, random_state=rng).as_quat() if m else np.zeros((0, 4))
    quats = np.concatenate([xyzw, fl_xyzw])[:, [3, 0, 1, 2]]
    return SampledMap(
        means=np.concatenate([means, fl]),
        scales=np.concatenate([scales, rng.uniform(0.005, 0.02, (m, 3))]),
        quats=quats,
        opacities=np.concatenate([opac, rng.uniform(0.05, 0.5, m)]),
        colors=np.concatenate([colors, rng.uniform(0.2, 0.8, (m, 3))]),
        primitive=np.concatenate([prim, np.full(m, -1, np.int32)]),
        spacing=spacing,
    )
