"""Masks whose ids hold for one frame only (`mask_ids: per_frame`): segments associated with map objects.

SAM-style segmenters, detectors with masks and panoptic networks number their segments per image
(METHOD.md section 9). Per keyframe, the map's current object labels are rendered into the view in
one pass (core.segments.label_render: per pixel the leading object, void included), and for every segment s
and rendered object o the overlap C[s, o] (pixels of s where o leads) is counted over the pixels
that both a segment and an object claim. Then:

1. Match, one to one (Hungarian, scipy linear_sum_assignment), segments to objects by IoU
   ``C[s, o] / (|s| + |o| - C[s, o])`` with sizes over those jointly claimed pixels, so that the
   part of a segment the map has not seen yet (rendered void) does not count against a match.
   Pairs below `min_iou` are never matched.
2. A segment left unmatched that lies mostly inside one object (``C[s, o] >= part_share * |s|`` and
   at least `part_coverage` of that object) is a piece of it (a split segment): it joins the object.
3. Any other segment of at least `new_object_fraction` of the image continues the object being born
   there, if any: where the map renders the segment as part of a larger object, the runner-up objects
   (each Gaussian's second most voted, rendered the same way: on demand, one more pass) show an object
   that an earlier keyframe started there; when one holds `part_share` of the segment, the segment is it.
   Otherwise it seeds a new object with a fresh display color (a packed 24-bit color never issued before,
   never white, black or the grey of unobserved points). Without this, an object hidden under a larger
   one's label (a segmenter fused them in earlier frames) was born again in every keyframe, and none of
   its births ever collected enough votes to lead. Smaller segments add no evidence this keyframe.
4. Objects are only ever matched by what is rendered: an object the view does not show (occluded,
   out of view, unobserved) gets no evidence and keeps its id. The first keyframe renders nothing,
   so its segments seed the objects.
5. Two objects whose rendered regions both lie mostly (`merge_containment`) inside one segment were
   "covered together"; when a pair was covered together in at least `merge_min_keyframes` keyframes
   and more often than it was seen apart (matched to two different segments), the younger object is
   merged into the older one: their votes add (VoteState.merge_objects), exactly.
6. Until then, a segment that covers two or more such objects, each at least `split_share` of it, is
   split along the map's rendered labels (a segmenter fused touching objects, or the map has not yet
   merged two objects of one): each of its pixels goes to the object rendered there when that object is
   one of the covered ones and leads the pixel with at least `split_confidence` of its weight; its other
   pixels add nothing. Given to one object, the fused segment's pixels were voted into the other in
   every frame that fused them. A split segment's class name (segment labels) is dropped: it names one
   of the objects, not which.
7. Where the segments carry class names (segment labels, core.segments.segment_labels), an object whose names add
   up to `name_min_score` is named, and a segment whose name holds less than `name_share` of an object's
   names is another object: its pixels where the map renders that object count as unclaimed (as void) in
   stages 1, 2 and 5, so it is never matched to it, and two objects named differently are never merged.
   Stage 3 (whose runner-up objects are checked against the name) and stage 6 read the rendering as it
   is: a named segment that covers two objects is still split along their rendered labels.
   Without this, an object whose Gaussians a fused segment once voted into its neighbour was taken over by
   that neighbour where the neighbour's segment covered it best, and the object itself was born again in
   every keyframe (office_0: the desk organizer took the tissue box's id).

The result of a keyframe is its mask relabeled with object colors (unassigned pixels void), which
the mapper integrates through the ordinary vote path, so everything downstream (palette, objects,
views) sees a mask with global ids.
"""

from __future__ import annotations

import json
import time
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field

import numpy as np

from monovoc_ros.core.evidence.palette import UNOBSERVED_ID, VOID_ID, pack_rgb, unpack_rgb
from monovoc_ros.core.segments.segment_labels import SegmentLabel, leading_name

MASK_ID_MODES = ("global", "per_frame")
# Colors never issued to a new object: void white, black and the grey unobserved points are drawn in.
_RESERVED = {VOID_ID, 0x000000, 0x808080}


@dataclass
class AssociationConfig:
    min_iou: float = 0.25  # stage 1: least IoU of a segment-object match
    part_share: float = 0.6  # stage 2: least share of the segment's claimed pixels inside the object
    part_coverage: float = 0.2  # stage 2: least share of the object's rendered pixels the piece covers
    new_object_fraction: float = 2e-4  # stage 3: least segment size (fraction of the image) for a new object
    merge_containment: float = 0.6  # stage 5: share of an object's rendered region inside the one segment
    merge_min_keyframes: int = 3  # stage 5: keyframes a pair must have been covered together
    # Stage 5: least segmenter score of a segment that counts as covering two objects together. A detector's
    # unsure mask bleeds over a partly hidden neighbour; only confident masks say two objects are one.
    merge_min_score: float = 0.5
    # Overlaps are counted on every render_scale-th pixel (the view rendered at 1/render_scale of the
    # mask's resolution): they are ratios of areas, and the rendering is most of the cost.
    render_scale: int = 2  # MapperConfig.association_scale
    # Stage 6: least share of a pixel's rendering weight its leading object must hold for a split segment's
    # pixel to go to that object.
    split_confidence: float = 0.5
    split_share: float = 0.2  # stage 6: least share of the segment's claimed pixels each covered object holds
    name_min_score: float = 2.0  # stage 7: summed segment-name score from which an object is named
    name_share: float = 0.2  # stage 7: least share of a named object's names a segment's name must hold

    def __post_init__(self) -> None:
        names = (
            "min_iou",
            "part_share",
            "part_coverage",
            "new_object_fraction",
            "merge_containment",
            "split_confidence",
            "split_share",
            "name_share",
        )
        for name in names:
            value = float(getattr(self, name))
            if not 0.0 < value <= 1.0:
                raise ValueError(f"association {name} must be in (0, 1], got {value!r}")
        if int(self.render_scale) < 1:
            raise ValueError(f"association render_scale must be >= 1, got {self.render_scale!r}")
        if not float(self.name_min_score) > 0.0:
            raise ValueError(f"association name_min_score must be > 0, got {self.name_min_score!r}")
        if not 0.0 <= float(self.merge_min_score) <= 1.0:
            raise ValueError(f"association merge_min_score must be in [0, 1], got {self.merge_min_score!r}")
        if int(self.merge_min_keyframes) < 1:
            raise ValueError(f"association merge_min_keyframes must be >= 1, got {self.merge_min_keyframes!r}")


def display_color(k: int) -> int:
    """The k-th display color of the sequence new objects draw from (packed 24-bit), well spread in
    hue (golden ratio) with saturation and value from a second low-discrepancy sequence."""
    h = (k * 0.6180339887498949) % 1.0
    s = 0.55 + 0.45 * ((k * 0.7548776662466927 + 0.3) % 1.0)
    v = 0.55 + 0.45 * ((k * 0.5698402909980532 + 0.6) % 1.0)
    i = int(h * 6.0) % 6
    f = h * 6.0 - int(h * 6.0)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    r, g, b = [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i]
    rgb = np.array([[round(255 * r), round(255 * g), round(255 * b)]], np.uint8)
    return int(pack_rgb(rgb)[0])


@dataclass
class Association:
    """One keyframe's association."""

    segment_objects: np.ndarray  # (S,) uint32 object id per segment, UNOBSERVED_ID = no evidence
    matched: int = 0  # segments matched one to one to a rendered object
    parts: int = 0  # segments joined to an object as a piece of it
    continued: int = 0  # segments given to the object being born where they lie (the runner-up rendering)
    new: int = 0  # segments that seeded a new object
    skipped: int = 0  # segments too small to seed an object
    rendered_objects: int = 0  # objects leading at least one pixel of the view
    merges: list[tuple[int, int]] = field(default_factory=list)  # (kept, merged away) object ids
    # Stage 6: segment index -> the object ids its pixels are split between (along the rendered labels).
    split: dict[int, np.ndarray] = field(default_factory=dict)
    seconds: float = 0.0  # the whole association of the keyframe (associate_keyframe), or the matching alone
    segment_seconds: float = 0.0  # associate_keyframe: the mask's segments (pixel labels)
    render_seconds: float = 0.0  # associate_keyframe: the map's labels rendered into the view


@dataclass(frozen=True)
class SegmentNames:
    """Stage 7: the class names of one keyframe's segments and those the map's objects were given."""

    segments: tuple[str | None, ...]  # (S,) per segment index, None = unnamed
    objects: Mapping[int, Mapping[str, float]]  # object id -> class name -> summed score (LabelHistogram.scores)
    scores: tuple[float, ...] = ()  # (S,) the segmenter's score per segment index (1 = unnamed); () = all 1

    def confident(self, config: AssociationConfig) -> np.ndarray:
        """(S,) bool: segments scored at least merge_min_score (stage 5 counts only those)."""
        if not self.scores:
            return np.ones(len(self.segments), bool)
        return np.asarray(self.scores, np.float64) >= config.merge_min_score

    def named(self, object_id: int, config: AssociationConfig) -> tuple[Mapping[str, float], float] | None:
        """(the object's names, their summed score) when that reaches name_min_score, else None."""
        table = self.objects.get(int(object_id))
        total = sum(table.values()) if table else 0.0
        return (table, total) if table and total >= config.name_min_score else None

    def conflicts(self, object_ids: np.ndarray, config: AssociationConfig) -> np.ndarray:
        """(S, R) bool: segment s is named and object `object_ids[r]` is named otherwise (never the same)."""
        out = np.zeros((len(self.segments), len(object_ids)), bool)
        for r, oid in enumerate(object_ids.tolist()):
            named = self.named(oid, config)
            if named is None:
                continue
            table, total = named
            for s, name in enumerate(self.segments):
                out[s, r] = name is not None and table.get(name, 0.0) < config.name_share * total
        return out

    def differ(self, a: int, b: int, config: AssociationConfig) -> bool:
        """Both objects named, with different leading names."""
        na, nb = self.named(a, config), self.named(b, config)
        return na is not None and nb is not None and leading_name(na[0]) != leading_name(nb[0])


def overlap_counts(segments: np.ndarray, n_segments: int, rendered: np.ndarray, n_rendered: int) -> np.ndarray:
    """(S, R) int64 pixel counts C[s, o] of segment s (labels (H, W) in [-1, S)) where rendered object
    o leads (rendered (H, W) in [-1, R)); -1 pixels are left out."""
    seg = segments.reshape(-1).astype(np.int64)
    ren = rendered.reshape(-1).astype(np.int64)
    both = (seg >= 0) & (ren >= 0)
    flat = np.bincount(seg[both] * n_rendered + ren[both], minlength=n_segments * n_rendered)
    return flat.reshape(n_segments, n_rendered)


def overlap_counts_reference(segments: np.ndarray, n_segments: int, rendered: np.ndarray, n_rendered: int):
    """Plain twin of overlap_counts."""
    out = np.zeros((n_segments, n_rendered), np.int64)
    for s, o in zip(segments.reshape(-1).tolist(), rendered.reshape(-1).tolist(), strict=True):
        if s >= 0 and o >= 0:
            out[s, o] += 1
    return out


class Associator:
    """Per-frame segments to map objects (see the module docstring); keeps the issued ids and the
    pair statistics between keyframes (and in snapshots: to_json / from_json)."""

    def __init__(self, config: AssociationConfig | None = None) -> None:
        self.config = config or AssociationConfig()
        self.issued: list[int] = []  # object ids in the order they were issued
        self._rank: dict[int, int] = {}  # object id -> its position in `issued`
        self._next_color = 0
        self.together: Counter[tuple[int, int]] = Counter()  # pair (older, younger): keyframes covered together
        self.apart: Counter[tuple[int, int]] = Counter()  # pair: keyframes matched to two different segments
        self.merged_into: dict[int, int] = {}  # merged-away id -> the id it became

    # ------------------------------------------------------------------ ids

    def _order(self, a: int, b: int) -> tuple[int, int]:
        """The pair as (older, younger) by issue order."""
        far = len(self.issued)
        return (a, b) if self._rank.get(a, far) < self._rank.get(b, far) else (b, a)

    def new_object(self, taken: set[int] | None = None) -> int:
        """A fresh object id: the next display color not issued yet (nor in `taken`)."""
        while True:
            color = display_color(self._next_color)
            self._next_color += 1
            if color not in self._rank and color not in _RESERVED and (taken is None or color not in taken):
                self._rank[color] = len(self.issued)
                self.issued.append(color)
                return color

    def resolve(self, object_id: int) -> int:
        """The live id an object id stands for now (following merges)."""
        while object_id in self.merged_into:
            object_id = self.merged_into[object_id]
        return object_id

    def adopt_ids(self, old: Associator, matches: Mapping[int, int]) -> dict[int, int]:
        """After a rebuild (core.segments.object_match): this associator, which issued the rebuilt state's ids,
        takes over from `old`, whose ids the map's users know. A rebuilt object in `matches` (rebuilt id -> old
        id, one to one) takes its old object's id; any other keeps its own id when `old` never issued it, else
        gets a fresh one that neither issued. Every id `old` issued stays issued, so none is ever given to
        another object later. The pair statistics and merges follow the ids (issue order: this associator's).
        Returns the renaming (rebuilt id -> id now, every id this associator issued) that the evidence, the
        palette and the segment labels must take (SemanticMapper.rename_objects)."""
        if len(set(matches.values())) != len(matches) or not set(matches) <= set(self._rank):
            raise ValueError("adopt_ids: matches must pair ids this associator issued one to one")
        if not set(matches.values()) <= set(old._rank):
            raise ValueError("adopt_ids: matches must name ids the old associator issued")
        self._next_color = max(self._next_color, old._next_color)
        mapping: dict[int, int] = {}
        for oid in self.issued:
            if oid in matches:
                mapping[oid] = int(matches[oid])
            elif oid not in old._rank:
                mapping[oid] = oid  # never known downstream: nothing to keep, nothing it could be mistaken for
            else:  # the old map's id of another object: fresh
                while True:
                    color = display_color(self._next_color)
                    self._next_color += 1
                    if color not in old._rank and color not in self._rank and color not in _RESERVED:
                        break
                mapping[oid] = color
        issued = [mapping[o] for o in self.issued]
        now = set(issued)
        issued += [o for o in old.issued if o not in now]  # reserved: dead ids of the old map
        self.issued = issued
        self._rank = {o: i for i, o in enumerate(issued)}
        for name in ("together", "apart"):
            table: Counter[tuple[int, int]] = Counter()
            for (a, b), n in getattr(self, name).items():
                table[self._order(mapping[a], mapping[b])] += n
            setattr(self, name, table)
        merged = {mapping[a]: mapping[b] for a, b in self.merged_into.items()}
        # The old map's merges keep resolving (its merged-away ids are dead here too, never a live id).
        self.merged_into = {**{a: b for a, b in old.merged_into.items() if a not in now}, **merged}
        return mapping

    # ------------------------------------------------------------------ association

    def associate(
        self,
        segments: np.ndarray,
        n_segments: int,
        rendered: np.ndarray,
        rendered_ids: np.ndarray,
        runner_up: Callable[[], tuple[np.ndarray, np.ndarray]] | None = None,
        names: SegmentNames | None = None,
    ):
        """Object id per segment. `segments` (H, W) int32 segment index (-1 = none), `rendered` (H, W)
        int32 index into `rendered_ids` ((R,) uint32 object ids) of the leading object (-1 = void);
        `runner_up()`: the same for the runner-up objects (stage 3), called at most once, when needed;
        `names`: the segments' class names and the objects' (stage 7).
        Updates the pair statistics and returns an Association whose `merges` the caller must apply
        to the evidence (merged-away ids never come back)."""
        start = time.perf_counter()
        cfg = self.config
        n_rendered = len(rendered_ids)
        out = np.full(n_segments, UNOBSERVED_ID, np.uint32)
        report = Association(out)
        seg_pixels = np.bincount(segments.reshape(-1)[segments.reshape(-1) >= 0], minlength=n_segments)
        if n_rendered:
            C = overlap_counts(segments, n_segments, rendered, n_rendered)
        else:
            C = np.zeros((n_segments, 0), np.int64)
        raw = C  # stages 3 and 6 read what the map renders, names aside
        raw_claimed = raw.sum(axis=1)  # (S,)
        if names is not None:  # the segment's name says the object rendered there is not what it shows
            C = np.where(names.conflicts(rendered_ids, cfg), 0, C)
        seg_claimed = C.sum(axis=1)  # (S,) pixels of s where some object leads
        obj_claimed = C.sum(axis=0)  # (R,) pixels of o inside some segment
        report.rendered_objects = int((obj_claimed > 0).sum())
        min_pixels = max(1, int(round(cfg.new_object_fraction * segments.size)))
        matched_obj = np.full(n_segments, -1, np.int64)  # stage-1 object index per segment
        if n_rendered and n_segments:
            union = seg_claimed[:, None] + obj_claimed[None, :] - C
            iou = np.divide(C, union, out=np.zeros(C.shape), where=union > 0)
            from scipy.optimize import linear_sum_assignment

            rows, cols = linear_sum_assignment(-iou)
            ok = iou[rows, cols] >= cfg.min_iou
            matched_obj[rows[ok]] = cols[ok]
            out[rows[ok]] = rendered_ids[cols[ok]]
            report.matched = int(ok.sum())
        second: tuple[np.ndarray, np.ndarray] | None = None  # (overlap counts, ids) of the runner-up rendering
        for s in np.flatnonzero(matched_obj < 0):
            if n_rendered and seg_claimed[s] > 0:
                o = int(np.argmax(C[s]))
                if C[s, o] >= cfg.part_share * seg_claimed[s] and C[s, o] >= cfg.part_coverage * obj_claimed[o]:
                    out[s] = rendered_ids[o]
                    report.parts += 1
                    continue
            if seg_pixels[s] < min_pixels:
                report.skipped += 1
                continue
            if runner_up is not None and raw_claimed[s] > 0:
                if second is None:
                    labels2, ids2 = runner_up()
                    C2 = overlap_counts(segments, n_segments, labels2, len(ids2))
                    if names is not None:
                        C2 = np.where(names.conflicts(ids2, cfg), 0, C2)
                    second = (C2, ids2)
                C2, ids2 = second
                n = int(np.argmax(C2[s])) if C2.shape[1] else -1
                if n >= 0 and C2[s, n] >= cfg.part_share * raw_claimed[s] and ids2[n] not in out:
                    out[s] = ids2[n]
                    report.continued += 1
                    continue
            out[s] = self.new_object()
            report.new += 1
        if n_rendered and n_segments:
            report.merges = self._pair_statistics(C, obj_claimed, matched_obj, rendered_ids, min_pixels, names)
            for keep, drop in report.merges:
                out[out == drop] = keep
            report.split = self._fused_segments(raw, raw.sum(axis=0), rendered_ids, min_pixels)
        report.seconds = time.perf_counter() - start
        return report

    def _fused_segments(self, C, obj_claimed, rendered_ids, min_pixels) -> dict[int, np.ndarray]:
        """Stage 6: segment -> the (live, distinct) ids of the two or more objects it covers, each a good part
        of it (a sliver of a neighbour rendered across the segment's border is no fusion)."""
        cfg = self.config
        inside = (C >= cfg.merge_containment * obj_claimed[None, :]) & (obj_claimed >= min_pixels)[None, :]
        inside &= C >= cfg.split_share * C.sum(axis=1, keepdims=True)
        split = {}
        for s in np.flatnonzero(inside.sum(axis=1) >= 2):
            ids = np.unique([self.resolve(int(rendered_ids[o])) for o in np.flatnonzero(inside[s])]).astype(np.uint32)
            if ids.size >= 2:  # objects merged just now are one
                split[int(s)] = ids
        return split

    def _pair_statistics(self, C, obj_claimed, matched_obj, rendered_ids, min_pixels, names) -> list[tuple[int, int]]:
        cfg = self.config
        visible = obj_claimed >= min_pixels
        inside = (C >= cfg.merge_containment * obj_claimed[None, :]) & visible[None, :]  # (S, R)
        if names is not None:
            inside &= names.confident(cfg)[:, None]
        for s in np.flatnonzero(inside.sum(axis=1) >= 2):
            objs = [int(rendered_ids[o]) for o in np.flatnonzero(inside[s])]
            for i, a in enumerate(objs):
                for b in objs[i + 1 :]:
                    self.together[self._order(a, b)] += 1
        seen = sorted(int(rendered_ids[o]) for o in matched_obj[matched_obj >= 0] if visible[o])
        for i, a in enumerate(seen):
            for b in seen[i + 1 :]:
                self.apart[self._order(a, b)] += 1
        merges = []
        for pair, n in list(self.together.items()):
            keep, drop = pair
            if n >= cfg.merge_min_keyframes and n > self.apart.get(pair, 0):
                if keep in self.merged_into or drop in self.merged_into:
                    continue
                if names is not None and names.differ(keep, drop, cfg):
                    continue
                merges.append((keep, drop))
                self._forget(drop, keep)
        return merges

    def _forget(self, drop: int, keep: int) -> None:
        """Pair statistics after `drop` became `keep`: pairs with drop are dropped (keep's own stay)."""
        self.merged_into[drop] = keep
        for table in (self.together, self.apart):
            for pair in [p for p in table if drop in p]:
                del table[pair]

    # ------------------------------------------------------------------ keyframes

    def relabel_mask(
        self,
        segments: np.ndarray,
        report: Association,
        rendered_ids: np.ndarray | None = None,
        rendered: np.ndarray | None = None,
        weights: np.ndarray | None = None,
    ) -> np.ndarray:
        """(H, W, 3) uint8 mask with each segment's pixels in its object's color, the rest void. Pixels of a
        split segment (report.split) take the object rendered there: `rendered` (H, W) index into
        `rendered_ids` (-1 = void) and `weights` (H, W) its share of the pixel, at the mask's resolution."""
        table = np.append(report.segment_objects, np.uint32(UNOBSERVED_ID))  # index -1 -> no evidence
        ids = table[segments]
        if report.split:
            assert rendered_ids is not None and rendered is not None and weights is not None
            live = np.array([self.resolve(int(o)) for o in rendered_ids], np.uint32)
            drawn = np.where(rendered >= 0, np.append(live, np.uint32(UNOBSERVED_ID))[rendered], UNOBSERVED_ID)
            sure = weights >= self.config.split_confidence
            for s, objects in report.split.items():
                pixels = segments == s
                here = drawn[pixels]
                ids[pixels] = np.where(np.isin(here, objects) & sure[pixels], here, UNOBSERVED_ID)
        ids = np.where(ids == UNOBSERVED_ID, np.uint32(VOID_ID), ids)
        return unpack_rgb(ids.astype(np.uint32))

    # ------------------------------------------------------------------ persistence

    def to_json(self) -> str:
        return json.dumps(
            {
                "config": asdict(self.config),
                "issued": self.issued,
                "next_color": self._next_color,
                "together": [[a, b, n] for (a, b), n in sorted(self.together.items())],
                "apart": [[a, b, n] for (a, b), n in sorted(self.apart.items())],
                "merged_into": sorted(self.merged_into.items()),
            }
        )

    @classmethod
    def from_json(cls, text: str) -> Associator:
        data = json.loads(text)
        out = cls(AssociationConfig(**data["config"]))
        out.issued = [int(o) for o in data["issued"]]
        out._rank = {o: i for i, o in enumerate(out.issued)}
        out._next_color = int(data["next_color"])
        out.together = Counter({(int(a), int(b)): int(n) for a, b, n in data["together"]})
        out.apart = Counter({(int(a), int(b)): int(n) for a, b, n in data["apart"]})
        out.merged_into = {int(a): int(b) for a, b in data["merged_into"]}
        return out


def compact_index_reference(gaussian_ids: np.ndarray, table: np.ndarray) -> np.ndarray:
    """Plain twin of label_render_kernels.compact_index: (N,) int32 position of each id in the sorted
    `table`, -1 where unobserved, -2 where absent."""
    pos = np.searchsorted(table, gaussian_ids).clip(0, max(table.size - 1, 0))
    found = table[pos] == gaussian_ids if table.size else np.zeros(len(gaussian_ids), bool)
    out = np.where(found, pos, -2).astype(np.int32)
    out[gaussian_ids == UNOBSERVED_ID] = -1
    return out


def rendered_object_index(gaussian_ids: np.ndarray, issued: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """(N,) int32 compact index of each Gaussian's object (-1 = unobserved) and (R,) uint32 the ids.

    With every id among `issued` (the per-frame case) a binary search over the issued ids replaces
    sorting the Gaussians' ids."""
    from monovoc_ros.core.segments.label_render_kernels import compact_index

    gaussian_ids = np.ascontiguousarray(gaussian_ids, np.uint32)
    table = np.unique(np.asarray(issued, np.uint32))
    if table.size:
        compact = np.empty(len(gaussian_ids), np.int32)
        if compact_index(gaussian_ids, table, np.uint32(UNOBSERVED_ID), compact) == 0:
            # Only the ids some Gaussian holds: merged-away ids would grow every overlap matrix with the run.
            present = np.bincount(compact[compact >= 0], minlength=table.size) > 0
            if present.all():
                return compact, table
            renumber = np.cumsum(present, dtype=np.int32) - 1
            return np.where(compact >= 0, renumber[np.maximum(compact, 0)], -1).astype(np.int32), table[present]
    known = gaussian_ids != UNOBSERVED_ID
    ids, index = np.unique(gaussian_ids[known], return_inverse=True)
    compact = np.full(len(gaussian_ids), -1, np.int32)
    compact[known] = index
    return compact, ids.astype(np.uint32)


def associate_keyframe(
    associator: Associator,
    gaussians,
    gaussian_ids: np.ndarray,
    keyframe,
    *,
    metric: str = "cmc",
    min_snap_margin: float = 0.2,
    runner_up_ids: Callable[[], np.ndarray] | None = None,
    object_names: Mapping[int, Mapping[str, float]] | None = None,
):
    """One keyframe of per-frame segments: its segments (the mask's own palette, core.evidence.pixel_labels),
    the map's labels `gaussian_ids` (N,) rendered into its view, the association, and the keyframe
    with its mask relabeled in object colors. `runner_up_ids()`: (N,) each Gaussian's runner-up object
    (VoteState.runner_up), rendered only when the association needs it. `object_names`: object id -> class
    name -> summed score (LabelHistogram.scores), for the keyframe's named segments (stage 7). Returns
    (keyframe, Association)."""
    from dataclasses import replace

    from monovoc_ros.core.evidence.pixel_labels import mask_labels
    from monovoc_ros.core.map.camera import resize_nearest
    from monovoc_ros.core.segments.label_render import render_label_weights

    start = time.perf_counter()
    labelled, _ = mask_labels(keyframe.mask, metric, min_snap_margin)
    segmented = time.perf_counter()
    compact, ids = rendered_object_index(gaussian_ids, associator.issued)
    k, scale = keyframe.intrinsics, int(associator.config.render_scale)
    small = k.scaled_to(max(1, k.width // scale), max(1, k.height // scale)) if scale > 1 else k
    segments_small = resize_nearest(labelled.labels, small.height, small.width) if scale > 1 else labelled.labels
    if ids.size:
        rendering = render_label_weights(gaussians, compact, small, keyframe.cam_to_world)
        rendered, weights = rendering.labels, rendering.weights
    else:
        rendered = np.full(segments_small.shape, -1, np.int32)
        weights = np.zeros(segments_small.shape, np.float32)
    drawn = time.perf_counter()

    def runner_up() -> tuple[np.ndarray, np.ndarray]:
        compact2, ids2 = rendered_object_index(runner_up_ids(), associator.issued)
        if not ids2.size:
            return np.full(segments_small.shape, -1, np.int32), ids2
        return render_label_weights(gaussians, compact2, small, keyframe.cam_to_world).labels, ids2

    names = None
    if keyframe.segments and object_names is not None:
        by_color = {s.id: s.class_name for s in keyframe.segments if s.score > 0}  # as LabelHistogram counts
        score = {s.id: float(s.score) for s in keyframe.segments}
        colors = labelled.objects.tolist()
        names = SegmentNames(
            tuple(by_color.get(c) for c in colors), object_names, tuple(score.get(c, 1.0) for c in colors)
        )
    report = associator.associate(
        segments_small, len(labelled.objects), rendered, ids, runner_up if runner_up_ids is not None else None, names
    )
    if report.split and scale > 1:  # split segments follow the rendered labels at the mask's resolution
        h, w = labelled.labels.shape
        rendered, weights = resize_nearest(rendered, h, w), resize_nearest(weights, h, w)
    mask = associator.relabel_mask(labelled.labels, report, ids, rendered, weights)
    segments = keyframe.segments
    if segments:  # the segment labels follow their segments to the objects; a split segment's name is dropped
        objects = np.where(np.isin(np.arange(len(labelled.objects)), list(report.split)), UNOBSERVED_ID,
                           report.segment_objects)  # fmt: skip
        table = dict(zip(labelled.objects.tolist(), objects.tolist(), strict=True))
        segments = tuple(
            SegmentLabel(table[s.id], s.class_name, s.score)
            for s in segments
            if table.get(s.id, UNOBSERVED_ID) != UNOBSERVED_ID
        )
    report.seconds = time.perf_counter() - start
    report.segment_seconds, report.render_seconds = segmented - start, drawn - segmented
    return replace(keyframe, mask=mask, segments=segments), report
