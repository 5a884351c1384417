"""A Gaussian map of the room as a SLAM front-end would leave it after photometric optimisation.

What a converged 3DGS SLAM map looks like, and how each feature is produced here:

- Flat Gaussians on the observed outer surfaces: two tangent scales, a 1-2 mm normal scale, a little
  position noise along the normal, noisy opacities, colors from the same appearance model as the
  images, and a few floaters in free space.
- Only surfaces the trajectory observed carry Gaussians (``observe``, see ``visibility``): a SLAM system
  creates Gaussians from its keyframes, so nothing appears under the table top or behind the sofa.
- Edge-adapted sizes. Optimisation against the keyframes shrinks Gaussians whose footprint spills over a
  silhouette, so near an edge of its face a Gaussian's sigma *across* that edge is at most its distance
  to the edge over ``EDGE_SIGMAS`` (its 2-sigma footprint stays on the face), while the axis along the
  edge keeps its size. Edges are the face's own (box and room-face rectangles, cylinder rims) and
  contacts (where the face meets another solid: a box standing on the table, the floor along the sofa).
  On curved faces the sigma along the curvature is bounded so the flat disc does not stand off the
  surface by more than ``CURVATURE_SAG``. Sizes never go below ``min_tangent_scale``.
- Densification near edges. 3DGS splits Gaussians where they shrink, so coverage stays. Here each face
  is a chart (``charts``) whose parameter square starts as a jittered grid of the base spacing; a cell
  splits (along the parameter axis that runs most across the binding limit) while it is more than
  ``SPLIT_RATIO`` target spacings across, the target spacing being the allowed sigma over
  ``TANGENT_SCALE_PER_SPACING``. Cells become narrow strips along edges, one Gaussian each, elongated
  along the edge, so the band gains Gaussians only across the edge (logarithmically many rows).

The requested count is met exactly: the base spacing is searched until the observed samples are just
above the count, then the surplus is dropped among unconstrained (interior) samples.
Surface samples that lie inside or against another solid (a leg's foot on the rug, a sofa's back against
the wall, a pole inside a lamp shade) are dropped: reconstruction never sees those faces.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from monovoc_ros.synthetic.appearance import Appearance
from monovoc_ros.synthetic.charts import CHART_KINDS, Chart
from monovoc_ros.synthetic.contacts import CONTACT_EPS, contact_limits, contact_limits_reference, neighbour_lists
from monovoc_ros.synthetic.primitives import Primitive, pack

GRID_JITTER = 0.5  # fraction of a grid cell a sample may move: uniform-looking, yet no large gaps
FLOATER_CLEARANCE = 0.10  # floaters keep this far from every surface, so they are unambiguous
TANGENT_SCALE_PER_SPACING = 0.8  # sigma of a splat in grid spacings: neighbours overlap, no holes
EDGE_SIGMAS = 2.0  # sigma across an edge <= distance to the edge / this: the 2-sigma footprint stays on the face
# Rendered through the rasterizer (every splat at least ~0.55 px wide after its 0.3 px^2 low-pass, at full
# opacity), a face covered up to its edge renders about a pixel too wide; optimisation against the
# keyframes pulls the last Gaussians in. In keyframe pixels at the primitive's typical depth:
EDGE_INSET_PX = 0.8  # the last Gaussians' centres stop this far inside a face's own edges
CURVED_INSET_PX = 1.2  # curved faces (silhouettes, no edges to stop at) sit this far inside the surface
MAX_INSET_FRACTION = 0.4  # insets at most this fraction of a face's half width (of a curved face's radius)
CURVATURE_SAG = 0.002  # metres a flat Gaussian's 2-sigma footprint may stand off a curved surface
SPLIT_RATIO = 1.4  # a cell splits when it spans more target spacings than this; halves land in (0.7, 1.4]
FLOOR_PER_SPACING = 0.07  # the sigma floor never falls below this many base spacings (2.5 mm at 140k)
MAX_SPLITS = 24  # per base cell: a safety bound, never reached with sigma floors of a millimetre or more
MAX_PASSES = 12  # spacing search passes; most maps need one to three
COUNT_SLACK = 0.025  # the spacing search stops once the samples exceed the count by at most this fraction
OWN_CAPS = 2  # most sigma caps a chart's own geometry sets at a point (two edges, or an edge and its rim)
Observer = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (points, normals) -> bool mask of observed ones


@dataclass(frozen=True)
class SampledMap:
    means: np.ndarray  # (N, 3)
    scales: np.ndarray  # (N, 3)
    quats: np.ndarray  # (N, 4) wxyz
    opacities: np.ndarray  # (N,)
    colors: np.ndarray  # (N, 3)
    primitive: np.ndarray  # (N,) int32 primitive index, -1 for floaters
    spacing: float  # base grid spacing reached (metres)


@dataclass(frozen=True)
class _Sites:
    """Surface samples with what bounds their Gaussians' sizes (the sigma caps and their directions)."""

    points: np.ndarray  # (n, 3)
    normals: np.ndarray  # (n, 3)
    tangents: np.ndarray  # (n, 3)
    primitive: np.ndarray  # (n,) int32
    caps: np.ndarray  # (n, K) largest sigma (m) along dirs[:, k]; inf where nothing bounds it
    dirs: np.ndarray  # (n, K, 3) unit tangents
    inward: np.ndarray  # (n,) offset (m) of the Gaussian's centre into the solid

    def __len__(self) -> int:
        return len(self.primitive)

    def take(self, index: np.ndarray) -> _Sites:
        return _Sites(self.points[index], self.normals[index], self.tangents[index], self.primitive[index],
                      self.caps[index], self.dirs[index], self.inward[index])  # fmt: skip


@dataclass(frozen=True)
class _Eval:
    """Chart points with whether they lie on their chart and the sigma caps of their own face."""

    points: np.ndarray
    normals: np.ndarray
    ta: np.ndarray
    tb: np.ndarray
    ga: np.ndarray
    gb: np.ndarray
    contains: np.ndarray  # (n,) bool
    caps: np.ndarray  # (n, OWN_CAPS) edges and curvature of the face itself; inf where unbounded
    dirs: np.ndarray  # (n, OWN_CAPS, 3)


class _Atlas:
    """Every chart of every primitive, evaluated in batches of (chart index, a, b): one call per chart kind."""

    def __init__(self, primitives: list[Primitive], pixel_size: np.ndarray | None = None) -> None:
        self.charts: list[Chart] = []
        owner = []
        for k, prim in enumerate(primitives):
            for chart in prim.charts():
                self.charts.append(chart)
                owner.append(k)
        self.owner = np.array(owner, np.int32)  # (C,) primitive index per chart
        self.kind = np.array([CHART_KINDS.index(type(c)) for c in self.charts], np.int32)
        self.row = np.zeros(len(self.charts), np.int64)  # row of each chart in its kind's parameter table
        self.tables = []
        for kind in range(len(CHART_KINDS)):
            members = np.flatnonzero(self.kind == kind)
            self.row[members] = np.arange(len(members))
            rows = [self.charts[c].params() for c in members]
            self.tables.append(np.stack(rows) if rows else np.zeros((0, 1)))
        px = np.zeros(len(primitives)) if pixel_size is None else np.asarray(pixel_size, float)
        pairs = list(zip(self.charts, owner, strict=True))
        # Edge inset per chart (m): how far inside its edges the last Gaussians stop (see EDGE_INSET_PX),
        # never more than a fraction of the face's half width, so thin faces keep their Gaussians.
        self.inset = np.array([min(EDGE_INSET_PX * px[k], MAX_INSET_FRACTION * c.half_width()) for c, k in pairs])
        # Inward offset per chart (m) of curved faces, whose silhouettes cannot be inset (CURVED_INSET_PX).
        self.inward = np.array(
            [min(CURVED_INSET_PX * px[k], MAX_INSET_FRACTION * c.radius) if c.curved else 0.0 for c, k in pairs]
        )
        # Where a face meets another solid the spill lands on that solid's own Gaussians, which hide it: no
        # inset beyond the contact tolerance.
        self.contact_inset = np.full(len(pairs), CONTACT_EPS)

    def evaluate(self, cid: np.ndarray, a: np.ndarray, b: np.ndarray, *, limits: bool = True) -> _Eval:
        n = len(cid)
        v3 = [np.zeros((n, 3)) for _ in range(4)]
        ga, gb, contains = np.zeros(n), np.zeros(n), np.zeros(n, bool)
        caps, dirs = np.full((n, OWN_CAPS), np.inf), np.zeros((n, OWN_CAPS, 3))
        kinds = self.kind[cid]
        for kind, cls in enumerate(CHART_KINDS):
            idx = np.flatnonzero(kinds == kind)
            if len(idx) == 0:
                continue
            P = self.tables[kind][self.row[cid[idx]]]
            ai, bi = a[idx], b[idx]
            p = cls.evaluate_packed(P, ai, bi)
            for dst, src in zip(v3, (p.points, p.normals, p.ta, p.tb), strict=True):
                dst[idx] = src
            ga[idx], gb[idx] = p.ga, p.gb
            lim = cls.limits_packed(P, ai, bi)
            inset = self.inset[cid[idx]]
            inside = np.ones(len(idx), bool)
            for d in lim.edge_distance:
                inside &= d >= inset
            contains[idx] = inside
            if not limits:
                continue
            col = 0
            for d, e, radius in zip(lim.edge_distance, lim.edge_direction, lim.edge_radius, strict=True):
                d = np.maximum(d - inset, 0.0)
                caps[idx, col], dirs[idx, col] = d / EDGE_SIGMAS, e
                col += 1
                if np.isfinite(radius).any():
                    # Along a convex rim the straight tangent leaves the face: from distance d inside a circle
                    # of radius R, it runs sqrt((R + sag)^2 - (R - d)^2) before standing out by sag.
                    reach = np.sqrt((radius + CURVATURE_SAG) ** 2 - (radius - np.minimum(d, radius)) ** 2)
                    caps[idx, col] = reach / 2
                    dirs[idx, col] = np.cross(p.normals, e)
                    col += 1
            for r, e in zip(lim.curvature_radius, lim.curvature_direction, strict=True):
                # A flat disc of half-width w = 2 sigma tangent to a circle of radius r stands off it by
                # about w^2 / 2r where it reaches sideways past a silhouette: keep that under CURVATURE_SAG.
                caps[idx, col], dirs[idx, col] = np.sqrt(2 * r * CURVATURE_SAG) / 2, e
                col += 1
        return _Eval(*v3, ga, gb, contains, caps, dirs)


class _Contacts:
    """Points hidden against another solid, and the sigma caps nearby solids impose (see ``contacts``)."""

    def __init__(self, primitives: list[Primitive], reach: float, *, reference: bool = False) -> None:
        self.primitives = primitives
        self.reach = reach  # neighbours farther than this bound nothing
        self.reference = reference  # the NumPy twin instead of the kernel (tests)
        self.kinds, self.params = pack(primitives)
        self.neighbours = neighbour_lists(primitives, reach + CONTACT_EPS)

    def __call__(
        self, prim: np.ndarray, points: np.ndarray, normals: np.ndarray, inset: np.ndarray, *, caps: bool = True
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(hidden (n,), caps (n, 2), dirs (n, 2, 3)): the two tightest caps from neighbouring solids."""
        kw = {"reach": self.reach, "edge_sigmas": EDGE_SIGMAS, "with_caps": caps}
        if self.reference:
            return contact_limits_reference(points, normals, prim, inset, self.neighbours, self.primitives, **kw)
        return contact_limits(points, normals, prim, inset, self.neighbours, self.kinds, self.params, **kw)


def _shape(
    normals: np.ndarray,
    tangents: np.ndarray,
    caps: np.ndarray,
    dirs: np.ndarray,
    s1: np.ndarray,
    s2: np.ndarray,
    psi: np.ndarray,
    floor: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Tangent axes (a1, a2) and sigmas (s1, s2) of Gaussians at most (s1, s2) large whose sigma along
    each cap's direction is at most the cap (then floored at ``floor``).

    An unbounded Gaussian keeps the in-plane orientation ``psi``; a bounded one turns its first axis across
    its tightest cap (it lies along that edge) and shrinks only that axis, as optimisation would. Further
    caps shrink the axis they mostly run across, or both axes where that does not suffice.
    """
    n = len(normals)
    rows = np.arange(n)
    tight = np.argmin(caps, axis=1)
    m0 = caps[rows, tight]
    e0 = dirs[rows, tight]
    e0 = e0 - np.sum(e0 * normals, axis=1, keepdims=True) * normals
    e0_len = np.linalg.norm(e0, axis=1, keepdims=True)
    active = (m0 < np.maximum(s1, s2)) & (e0_len[:, 0] > 1e-9)
    free = np.cos(psi)[:, None] * tangents + np.sin(psi)[:, None] * np.cross(normals, tangents)
    a1 = np.where(active[:, None], e0 / np.maximum(e0_len, 1e-12), free)
    a2 = np.cross(normals, a1)
    s1 = np.where(active, np.minimum(s1, m0), s1)
    s2 = np.array(s2, float, copy=True)
    for k in range(caps.shape[1]):
        m, e = caps[:, k], dirs[:, k]
        c, d = np.abs(np.sum(e * a1, axis=1)), np.abs(np.sum(e * a2, axis=1))
        norm = np.maximum(np.hypot(c, d), 1e-12)
        c, d = c / norm, d / norm
        bad = np.isfinite(m) & ((s1 * c) ** 2 + (s2 * d) ** 2 > m * m * (1 + 1e-9))
        if not bad.any():
            continue
        rest_for_2 = m * m - (s1 * c) ** 2  # what axis 2 may still have if axis 1 stays
        rest_for_1 = m * m - (s2 * d) ** 2
        only2 = bad & (d >= c) & (rest_for_2 > 0)
        only1 = bad & (c > d) & (rest_for_1 > 0)
        both = bad & ~only2 & ~only1
        s2 = np.where(only2, np.sqrt(np.maximum(rest_for_2, 0)) / np.maximum(d, 1e-12), s2)
        s1 = np.where(only1, np.sqrt(np.maximum(rest_for_1, 0)) / np.maximum(c, 1e-12), s1)
        f = np.where(both, m, 1.0) / np.sqrt(np.maximum((s1 * c) ** 2 + (s2 * d) ** 2, 1e-30))
        s1 = np.where(both, s1 * f, s1)
        s2 = np.where(both, s2 * f, s2)
    return a1, a2, np.maximum(s1, floor), np.maximum(s2, floor)


def _base_cells(atlas: _Atlas, spacing: float) -> tuple[np.ndarray, ...]:
    parts = []
    for c, chart in enumerate(atlas.charts):
        na, nb = chart.base_cells(spacing)
        ia, ib = np.meshgrid(np.arange(na), np.arange(nb), indexing="ij")
        n = na * nb
        parts.append(
            (np.full(n, c, np.int32), ia.ravel() / na, ib.ravel() / nb, np.full(n, 1 / na), np.full(n, 1 / nb))
        )
    return tuple(np.concatenate(x) for x in zip(*parts, strict=True))


def _leaves(atlas: _Atlas, contacts: _Contacts, spacing: float, floor: float, adaptive: bool) -> tuple[np.ndarray, ...]:
    """Leaf cells (chart, a0, b0, da, db): the base grid, split where Gaussians must be smaller than it."""
    cid, a0, b0, da, db = _base_cells(atlas, spacing)
    if not adaptive:
        return cid, a0, b0, da, db
    base = TANGENT_SCALE_PER_SPACING * spacing
    leaves: list[tuple[np.ndarray, ...]] = []
    for _ in range(MAX_SPLITS):
        if len(cid) == 0:
            break
        ac, bc = a0 + da / 2, b0 + db / 2
        p = atlas.evaluate(cid, ac, bc)
        prim = atlas.owner[cid]
        hidden, ccaps, cdirs = contacts(prim, p.points, p.normals, atlas.contact_inset[cid])
        culled = hidden | ~p.contains
        caps = np.concatenate([p.caps, ccaps], axis=1)
        dirs = np.concatenate([p.dirs, cdirs], axis=1)
        # A cell whose centre is off the face (hidden against a solid, or outside its disc) is dropped when
        # its corners are too (it lies inside a convex contact region or outside the disc); otherwise it
        # straddles the boundary and must be split down to the floor across it. Which corners are off
        # tells the boundary's run: corners differing along a mean a boundary across a.
        gone = culled.copy()
        idx = np.flatnonzero(culled)
        if len(idx):
            off = np.zeros((len(idx), 4), bool)
            for j, (fa, fb) in enumerate(((0, 0), (1, 0), (0, 1), (1, 1))):
                ca, cb = a0[idx] + fa * da[idx], b0[idx] + fb * db[idx]
                pc = atlas.evaluate(cid[idx], ca, cb, limits=False)
                hid = contacts(prim[idx], pc.points, pc.normals, atlas.contact_inset[cid[idx]], caps=False)[0]
                off[:, j] = ~pc.contains | hid
            gone[idx] = off.all(axis=1)
            across_a = (off[:, 0] != off[:, 1]) | (off[:, 2] != off[:, 3])
            across_b = (off[:, 0] != off[:, 2]) | (off[:, 1] != off[:, 3])
            neither = ~across_a & ~across_b
            caps[idx] = np.inf
            caps[idx, 0] = np.where(across_a | neither, 0.0, np.inf)
            caps[idx, 1] = np.where(across_b | neither, 0.0, np.inf)
            dirs[idx, 0], dirs[idx, 1] = p.ta[idx], p.tb[idx]
        n = len(cid)
        s = np.full(n, base)
        a1, a2, s1, s2 = _shape(p.normals, p.ta, caps, dirs, s, s, np.zeros(n), floor)

        def extent(e: np.ndarray, p: _Eval = p, da: np.ndarray = da, db: np.ndarray = db):
            return np.abs(np.sum(e * p.ta, axis=1)) * da * p.ga, np.abs(np.sum(e * p.tb, axis=1)) * db * p.gb

        e1a, e1b = extent(a1)
        e2a, e2b = extent(a2)
        r1 = (e1a + e1b) * TANGENT_SCALE_PER_SPACING / s1
        r2 = (e2a + e2b) * TANGENT_SCALE_PER_SPACING / s2
        # Only bounded cells split: the base grid already fits unbounded Gaussians.
        split = ~gone & (caps.min(axis=1) < base) & (np.maximum(r1, r2) > SPLIT_RATIO)
        done = ~gone & ~split
        leaves.append((cid[done], a0[done], b0[done], da[done], db[done]))
        # Halve along the parameter axis that spans most of the worst-bounded direction.
        along_a = np.where(r1 >= r2, e1a >= e1b, e2a >= e2b)
        sa, sb = split & along_a, split & ~along_a
        cid = np.concatenate([cid[sa], cid[sa], cid[sb], cid[sb]])
        a0 = np.concatenate([a0[sa], a0[sa] + da[sa] / 2, a0[sb], a0[sb]])
        b0 = np.concatenate([b0[sa], b0[sa], b0[sb], b0[sb] + db[sb] / 2])
        da, db = (
            np.concatenate([da[sa] / 2, da[sa] / 2, da[sb], da[sb]]),
            np.concatenate([db[sa], db[sa], db[sb] / 2, db[sb] / 2]),
        )
    leaves.append((cid, a0, b0, da, db))  # whatever MAX_SPLITS left unfinished
    return tuple(np.concatenate(x) for x in zip(*leaves, strict=True))


def _sites(
    atlas: _Atlas, contacts: _Contacts, spacing: float, rng: np.random.Generator, floor: float, adaptive: bool
) -> _Sites:
    """One jittered sample per leaf cell of every chart, minus those hidden against another solid."""
    cid, a0, b0, da, db = _leaves(atlas, contacts, spacing, floor, adaptive)
    n = len(cid)
    a = a0 + da * (0.5 + GRID_JITTER * rng.uniform(-0.5, 0.5, n))
    b = b0 + db * (0.5 + GRID_JITTER * rng.uniform(-0.5, 0.5, n))
    p = atlas.evaluate(cid, a, b, limits=adaptive)
    prim = atlas.owner[cid]
    hidden, ccaps, cdirs = contacts(prim, p.points, p.normals, atlas.contact_inset[cid], caps=adaptive)
    inward = atlas.inward[cid]
    moved = np.flatnonzero(~hidden & (inward > 0))
    if len(moved):
        # A curved face's Gaussians sit inside it; where another solid cuts in (the plant in its pot) they
        # must not end up inside that one.
        inner = p.points[moved] - inward[moved, None] * p.normals[moved]
        hidden[moved] = contacts(prim[moved], inner, p.normals[moved], atlas.contact_inset[cid[moved]], caps=False)[0]
    keep = np.flatnonzero(~hidden & p.contains)
    caps = np.concatenate([p.caps, ccaps], axis=1)
    dirs = np.concatenate([p.dirs, cdirs], axis=1)
    return _Sites(p.points[keep], p.normals[keep], p.ta[keep], prim[keep], caps[keep], dirs[keep],
                  inward[keep])  # fmt: skip


def _surface_sites_exact(
    atlas: _Atlas,
    contacts: _Contacts,
    n: int,
    rng: np.random.Generator,
    floor: float,
    adaptive: bool,
    observe: Observer | None,
) -> tuple[_Sites, float]:
    """Exactly ``n`` observed samples: search the base spacing until slightly more survive, drop the surplus.

    The count falls like spacing^-2 (edge bands included, their floor scaling with the spacing); the
    exponent is measured from the passes made so far (a secant step in log-log), and once a spacing too
    fine and one too coarse are known the step stays between them. The pass with the smallest count
    of at least ``n`` is kept.
    """
    area = sum(p.area() for p in contacts.primitives)
    spacing = float(np.sqrt(area / n))
    history: list[tuple[float, int]] = []
    target = n * (1 + COUNT_SLACK / 2)
    best: tuple[_Sites, float] | None = None
    fine, coarse = 0.0, np.inf  # largest spacing known to give >= n, smallest known to give < n
    for _ in range(MAX_PASSES):
        sites = _sites(atlas, contacts, spacing, rng, _floor(floor, spacing), adaptive)
        if observe is not None and len(sites):
            sites = sites.take(np.flatnonzero(observe(sites.points, sites.normals)))
        count = len(sites)
        if count >= n and (best is None or count < len(best[0])):
            best = (sites, spacing)
        if n <= count <= n * (1 + COUNT_SLACK):
            break
        if count >= n:
            fine = max(fine, spacing)
        else:
            coarse = min(coarse, spacing)
        history.append((spacing, max(count, 1)))
        slope = 2.0
        if len(history) >= 2:
            (s0, c0), (s1, c1) = history[-2], history[-1]
            if s0 != s1 and c0 != c1:
                slope = float(np.clip(-np.log(c1 / c0) / np.log(s1 / s0), 1.0, 3.0))
        spacing *= float((max(count, 1) / target) ** (1 / slope))
        if fine > 0 and np.isfinite(coarse) and not fine < spacing < coarse:
            spacing = float(np.sqrt(fine * coarse))
    if best is None:
        raise RuntimeError(f"could not place {n} surface samples")  # pragma: no cover - the search halves first
    sites, spacing = best
    surplus = len(sites) - n
    if surplus:
        # Drop where neighbours overlap most: unbounded (interior) samples, never the thin edge rows.
        free = np.flatnonzero(sites.caps.min(axis=1) >= TANGENT_SCALE_PER_SPACING * spacing)
        pool = free if len(free) >= surplus else np.arange(len(sites))
        drop = rng.choice(pool, surplus, replace=False)
        keep = np.ones(len(sites), bool)
        keep[drop] = False
        sites = sites.take(np.flatnonzero(keep))
    return sites, spacing


def _floor(min_tangent_scale: float, spacing: float) -> float:
    """Smallest tangent sigma at a base spacing: ``min_tangent_scale``, or more for a map of few Gaussians.

    Edge bands hold about log(base sigma / floor) rows of Gaussians per edge; a floor proportional to the
    spacing keeps that number fixed, so the count falls like spacing^-2 everywhere and a small budget is
    not spent on millimetre Gaussians along hundreds of metres of edges.
    """
    return max(min_tangent_scale, FLOOR_PER_SPACING * spacing)


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
    min_tangent_scale: float = 0.0025,
    edge_adaptive: bool = True,
    observe: Observer | None = None,
    pixel_size: np.ndarray | None = None,
) -> SampledMap:
    """``n_surface`` surface Gaussians and ``n_floaters`` floaters; ``observe`` keeps only observed surface
    points (None: every outer surface), ``edge_adaptive`` bounds sizes at edges and densifies there."""
    lo, hi = tangent_scale_range
    floor = min_tangent_scale if edge_adaptive else lo
    area = sum(p.area() for p in primitives)
    # Neighbours matter while they could bound a sigma below the largest interior size.
    reach = EDGE_SIGMAS * max(hi, 1.25 * TANGENT_SCALE_PER_SPACING * np.sqrt(area / max(n_surface, 1)))
    atlas = _Atlas(primitives, pixel_size if edge_adaptive else None)
    contacts = _Contacts(primitives, reach if edge_adaptive else 0.0)
    sites, spacing = _surface_sites_exact(atlas, contacts, n_surface, rng, floor, edge_adaptive, observe)
    n = len(sites)
    normals = sites.normals / np.linalg.norm(sites.normals, axis=1, keepdims=True)
    t1 = sites.tangents - np.sum(sites.tangents * normals, axis=1, keepdims=True) * normals
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)

    sigma = TANGENT_SCALE_PER_SPACING * spacing
    base1 = np.clip(sigma * rng.uniform(0.8, 1.25, n), lo, hi)
    base2 = np.clip(sigma * rng.uniform(0.8, 1.25, n), lo, hi)
    psi = rng.uniform(0, np.pi, n)  # orientation of the splat's long axis within the surface
    if edge_adaptive:
        a1, a2, s1, s2 = _shape(normals, t1, sites.caps, sites.dirs, base1, base2, psi, _floor(floor, spacing))
    else:
        a1 = np.cos(psi)[:, None] * t1 + np.sin(psi)[:, None] * np.cross(normals, t1)
        a2, s1, s2 = np.cross(normals, a1), base1, base2
    frames = np.stack([a1, a2, normals], axis=2)  # columns: tangent, tangent, normal
    scales = np.stack([s1, s2, rng.uniform(0.001, 0.002, n)], axis=1)
    opac = rng.uniform(0.6, 0.99, n)
    low = rng.random(n) < low_opacity_fraction
    opac[low] = rng.uniform(0.05, 0.5, int(low.sum()))
    prim = sites.primitive
    colors = appearance.color(prim, sites.points, normals)
    noise = rng.normal(0.0, surface_noise, (n, 1)) if surface_noise > 0 else np.zeros((n, 1))
    means = sites.points + normals * (noise - sites.inward[:, None])

    fl = _floaters(primitives, n_floaters, room_min, room_max, rng)
    m = len(fl)
    xyzw = Rotation.from_matrix(frames).as_quat() if n else np.zeros((0, 4))
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
