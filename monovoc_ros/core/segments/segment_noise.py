"""What a real segmenter does to masks, applied to masks with global ids (for tests and figures).

- `shuffle_ids`: every color of one mask renumbered at random (a SAM-style segmenter's per-image
  numbering): the segments stay, their ids hold for this mask only.
- `segment_noise`: per segment, with the stated probabilities (`NoiseRates`, each seeded per keyframe):
  * fusion: merged with an adjacent segment (touching instances, one segment);
  * parts: cut into 2..`pieces` parts, by the `cut` rule: "line" (parallel straight cuts across the
    segment at random positions and angle) or "voronoi" (the nearest of 2..`pieces` random seed pixels
    inside it: irregular parts);
  * missed: when smaller than `small_fraction` of the image, dropped to void;
  * boundary jitter: every boundary displaced by up to `jitter` pixels (a smooth random displacement
    field, so boundaries wander coherently, as a segmenter's do between frames);
  * granularity: with probability `granularity` a keyframe is segmented coarser (fusion rate doubled, no
    parts) and with the same probability finer (parts doubled, no fusion), so it changes between
    consecutive frames.
- A sequence whose keyframe masks went through both, deterministically per keyframe index, is
  `CorruptedMasks` (core.evaluation.datasets).

Void (pure white) pixels stay void; new colors are never white.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from monovoc_ros.core.evidence.palette import VOID_ID, pack_rgb, unpack_rgb


def _random_colors(n: int, rng: np.random.Generator, avoid: np.ndarray | None = None) -> np.ndarray:
    """(n,) distinct packed colors, none white, none in `avoid`."""
    out: list[int] = []
    banned = {VOID_ID} | (set(avoid.tolist()) if avoid is not None else set())
    while len(out) < n:
        for c in rng.integers(0, 0xFFFFFF, 2 * (n - len(out)) + 4).tolist():
            if c not in banned and len(out) < n:
                banned.add(c)
                out.append(c)
    return np.array(out, np.uint32)


def shuffle_ids(mask: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(H, W, 3) uint8 mask with every non-void color replaced by a random color of its own."""
    packed = pack_rgb(mask)
    colors, inverse = np.unique(packed, return_inverse=True)
    new = _random_colors(colors.size, rng)
    new[colors == VOID_ID] = VOID_ID
    return unpack_rgb(new[inverse].reshape(packed.shape))


def _adjacent_pairs(labels: np.ndarray) -> np.ndarray:
    """(P, 2) distinct unordered pairs of labels (>= 0) that touch horizontally or vertically."""
    a = np.concatenate([labels[:, :-1].ravel(), labels[:-1, :].ravel()])
    b = np.concatenate([labels[:, 1:].ravel(), labels[1:, :].ravel()])
    keep = (a != b) & (a >= 0) & (b >= 0)
    pairs = np.sort(np.stack([a[keep], b[keep]], axis=1), axis=1)
    return np.unique(pairs, axis=0) if len(pairs) else np.zeros((0, 2), labels.dtype)


CUTS = ("line", "voronoi")


@dataclass(frozen=True)
class NoiseRates:
    merge: float = 0.0  # probability that a segment is merged with one adjacent segment
    split: float = 0.0  # probability that a segment is cut into parts
    drop: float = 0.0  # probability that a small segment is dropped to void
    small_fraction: float = 0.002  # "small": fewer pixels than this fraction of the image
    pieces: int = 2  # a cut segment falls into 2..pieces parts
    cut: str = "line"  # how: 'line' (straight cuts) or 'voronoi' (nearest of random seeds)
    jitter: int = 0  # pixels by which boundaries wander
    granularity: float = 0.0  # probability of a coarser keyframe, and the same of a finer one

    def __post_init__(self) -> None:
        for name in ("merge", "split", "drop", "small_fraction"):
            if not 0.0 <= float(getattr(self, name)) <= 1.0:
                raise ValueError(f"segment noise {name} must be in [0, 1], got {getattr(self, name)!r}")
        if not 0.0 <= float(self.granularity) <= 0.5:
            raise ValueError(f"segment noise granularity must be in [0, 0.5], got {self.granularity!r}")
        if not 2 <= int(self.pieces) <= 16:
            raise ValueError(f"segment noise pieces must be in 2..16, got {self.pieces!r}")
        if self.cut not in CUTS:
            raise ValueError(f"segment noise cut must be one of {CUTS}, got {self.cut!r}")
        if not 0 <= int(self.jitter) <= 64:
            raise ValueError(f"segment noise jitter must be in 0..64 pixels, got {self.jitter!r}")

    @property
    def any(self) -> bool:
        return self.merge > 0 or self.split > 0 or self.drop > 0 or self.jitter > 0 or self.granularity > 0


def _parts(ys: np.ndarray, xs: np.ndarray, k: int, cut: str, rng: np.random.Generator) -> np.ndarray:
    """(P,) part index 0..k-1 of each pixel (ys, xs) of one segment."""
    if cut == "voronoi":
        seeds = rng.choice(len(ys), size=min(k, len(ys)), replace=False)
        d = (ys[:, None] - ys[seeds][None, :]) ** 2 + (xs[:, None] - xs[seeds][None, :]) ** 2
        return np.argmin(d, axis=1)
    angle = rng.uniform(0, np.pi)
    t = (xs - xs.mean()) * np.cos(angle) + (ys - ys.mean()) * np.sin(angle)
    # k - 1 cuts at random positions of the middle of the segment's extent along the direction.
    lo, hi = np.percentile(t, [20, 80]) if len(t) > 1 else (0.0, 0.0)
    cuts = np.sort(rng.uniform(lo, hi, k - 1))
    return np.searchsorted(cuts, t)


def _jittered(labels: np.ndarray, amplitude: int, rng: np.random.Generator) -> np.ndarray:
    """Labels resampled through a smooth random displacement of up to `amplitude` pixels."""
    h, w = labels.shape
    step = 16  # displacement nodes every 16 pixels, bilinear in between
    gh, gw = h // step + 2, w // step + 2
    field = rng.uniform(-amplitude, amplitude, (2, gh, gw))
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    gy, gx = yy / step, xx / step
    y0, x0 = np.floor(gy).astype(int), np.floor(gx).astype(int)
    fy, fx = gy - y0, gx - x0

    def sample(f: np.ndarray) -> np.ndarray:
        return (
            f[y0, x0] * (1 - fy) * (1 - fx) + f[y0 + 1, x0] * fy * (1 - fx)
            + f[y0, x0 + 1] * (1 - fy) * fx + f[y0 + 1, x0 + 1] * fy * fx
        )  # fmt: skip

    sy = np.clip(np.rint(yy + sample(field[0])), 0, h - 1).astype(int)
    sx = np.clip(np.rint(xx + sample(field[1])), 0, w - 1).astype(int)
    return labels[sy, sx]


def segment_noise(mask: np.ndarray, rates: NoiseRates, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """The mask with segments merged, cut into parts, dropped and jittered at `rates` (see the module
    docstring), and the counts of each."""
    packed = pack_rgb(mask)
    colors, inverse = np.unique(packed, return_inverse=True)
    labels = inverse.reshape(packed.shape).astype(np.int64)
    void = np.flatnonzero(colors == VOID_ID)
    if void.size:
        labels[labels == void[0]] = -1
    n = colors.size
    table = np.arange(n)  # label -> label it became (merges)
    counts = {"merged": 0, "split": 0, "dropped": 0, "coarse": 0, "fine": 0}
    if rates.granularity > 0:
        draw = rng.random()
        if draw < rates.granularity:  # a coarser keyframe: more fusions, no parts
            rates = replace(rates, merge=min(1.0, 2 * rates.merge), split=0.0)
            counts["coarse"] = 1
        elif draw < 2 * rates.granularity:  # a finer one: more parts, no fusions
            rates = replace(rates, merge=0.0, split=min(1.0, 2 * rates.split))
            counts["fine"] = 1
    if rates.merge > 0:
        pairs = _adjacent_pairs(labels)
        taken = np.zeros(n, bool)
        for s in rng.permutation(n).tolist():
            if taken[s] or colors[s] == VOID_ID or rng.random() >= rates.merge:
                continue
            mates = np.concatenate([pairs[pairs[:, 0] == s, 1], pairs[pairs[:, 1] == s, 0]])
            mates = mates[~taken[mates]]
            if mates.size:
                t = int(rng.choice(mates))
                table[t] = s
                taken[[s, t]] = True
                counts["merged"] += 1
        labels = np.where(labels >= 0, table[np.maximum(labels, 0)], -1)
    out = np.where(labels >= 0, colors[np.maximum(labels, 0)], np.uint32(VOID_ID)).astype(np.uint32)
    sizes = np.bincount(labels[labels >= 0], minlength=n)
    small = rates.small_fraction * labels.size
    fresh = _random_colors(n * (rates.pieces - 1), rng, colors).reshape(n, rates.pieces - 1)
    for s in np.flatnonzero(sizes).tolist():
        if sizes[s] < small and rates.drop > 0 and rng.random() < rates.drop:
            out[labels == s] = VOID_ID
            counts["dropped"] += 1
        elif sizes[s] >= 2 and rates.split > 0 and rng.random() < rates.split:
            ys, xs = np.nonzero(labels == s)
            k = int(rng.integers(2, rates.pieces + 1))
            part = _parts(ys, xs, k, rates.cut, rng)
            if np.unique(part).size > 1:
                moved = part > 0
                out[ys[moved], xs[moved]] = fresh[s][part[moved] - 1]
                counts["split"] += 1
    if rates.jitter > 0:
        out = _jittered(out, int(rates.jitter), rng)
    return unpack_rgb(out), counts


_NUMBERS = {"merge": float, "split": float, "drop": float, "small": float, "pieces": int, "jitter": int,
            "granularity": float}  # fmt: skip


def parse_mask_noise(spec: str) -> tuple[bool, NoiseRates]:
    """'shuffled', 'shuffled,merge=0.1,split=0.1', 'merge=0.1,split=0.1,pieces=4,cut=voronoi,jitter=2,granularity=0.2'
    ... -> (shuffled, rates)."""
    shuffled, values = False, {}
    for item in filter(None, (part.strip() for part in spec.split(","))):
        if item == "shuffled":
            shuffled = True
            continue
        name, eq, value = item.partition("=")
        if not eq or name not in (*_NUMBERS, "cut"):
            raise ValueError(
                "mask noise: expected shuffled, merge=P, split=P, drop=P, small=F, pieces=K, cut=line|voronoi, "
                f"jitter=PX or granularity=P, got {item!r}"
            )
        try:
            values["small_fraction" if name == "small" else name] = value if name == "cut" else _NUMBERS[name](value)
        except ValueError:
            raise ValueError(f"mask noise: {name} needs a number, got {value!r}") from None
    return shuffled, NoiseRates(**values)
