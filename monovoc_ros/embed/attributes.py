"""Measurable object attributes (color, size, height) and the text descriptions built from them.

ImageNet classes say nothing about "the red chair" or "the small box on the shelf"; the map knows each
object's pixels and 3D extent, so it can describe them and embed the description next to the crops.
"""

from __future__ import annotations

import re
import weakref
from collections.abc import Sequence

import numpy as np

from monovoc_ros.core.evidence.color import srgb_to_lab
from monovoc_ros.embed.arrays import l2_normalize

BASIC_COLORS = ("black", "white", "gray", "red", "orange", "yellow", "green", "blue", "purple", "pink", "brown")

# Prototype sRGB values for the chromatic basic color terms (Berlin & Kay), several per term so that
# light and dark variants land on the right name: nearest prototype in CIELAB (CIEDE2000) wins.
# Brown is dark/desaturated orange-red and pink is light red-purple, so lightness separates those pairs.
_CHROMATIC_PROTOTYPES: dict[str, tuple[tuple[int, int, int], ...]] = {
    "red": ((220, 30, 35), (160, 20, 25), (235, 70, 60)),
    "orange": ((255, 140, 0), (235, 105, 25), (255, 175, 70)),
    "yellow": ((255, 225, 0), (245, 235, 110), (215, 190, 30)),
    "green": ((0, 160, 60), (30, 90, 40), (130, 205, 90), (0, 180, 140), (110, 130, 40)),
    "blue": ((0, 70, 210), (20, 30, 110), (100, 160, 235), (0, 150, 205)),
    "purple": ((125, 40, 165), (70, 20, 95), (175, 115, 215)),
    "pink": ((255, 150, 190), (230, 80, 150), (255, 195, 205)),
    "brown": ((125, 75, 35), (80, 50, 25), (165, 115, 75), (100, 65, 50), (205, 170, 125)),
}
# Achromatic rules in CIELAB: below this chroma C*ab a color is black, gray or white by lightness L*.
ACHROMATIC_CHROMA = 12.0
BLACK_BELOW_L = 25.0
WHITE_ABOVE_L = 85.0
# Anything this dark is black (a navy blue above it stays blue) unless it keeps a clear hue: in a dimly
# exposed scene (Replica office_0) a blue recycling bin has L* 8.5 and chroma 15, a black bin chroma 4.5.
ALWAYS_BLACK_BELOW_L = 12.0
DARK_HUE_MIN_CHROMA = 15.0
# Per-object pixel budget: colors are named per pixel and voted; an evenly strided subset is plenty.
MAX_COLOR_PIXELS = 4096

# Size words by the largest extent (m), relative to typical indoor objects: a mug is tiny, a shoebox
# small, a chair needs no word, a sofa or wardrobe is large.
_SIZE_WORDS = ((0.1, "tiny"), (0.35, "small"), (1.5, ""), (float("inf"), "large"))
# Objects whose bottom is at most this high count as standing on the floor (no height phrase).
ON_FLOOR_MAX_M = 0.15


_PROTOTYPE_CACHE: dict[str, np.ndarray] = {}


_BLACK, _WHITE, _GRAY = (BASIC_COLORS.index(name) for name in ("black", "white", "gray"))


def _prototypes() -> tuple[np.ndarray, np.ndarray]:
    """(P,) int64 the BASIC_COLORS index of each chromatic prototype, (P, 3) float64 their CIELAB values."""
    if "lab" not in _PROTOTYPE_CACHE:
        rgb = np.array([c for cs in _CHROMATIC_PROTOTYPES.values() for c in cs], dtype=np.uint8)
        _PROTOTYPE_CACHE["lab"] = srgb_to_lab(rgb)
        names = [name for name, cs in _CHROMATIC_PROTOTYPES.items() for _ in cs]
        _PROTOTYPE_CACHE["codes"] = np.array([BASIC_COLORS.index(name) for name in names], np.int64)
    return _PROTOTYPE_CACHE["codes"], _PROTOTYPE_CACHE["lab"]


def color_names(pixels: np.ndarray) -> list[str]:
    """Basic color term of each sRGB uint8 pixel of an (n, 3) array."""
    return [BASIC_COLORS[c] for c in _color_codes(pixels).tolist()]


def color_names_reference(pixels: np.ndarray) -> list[str]:
    """Plain twin of `color_names`: every pixel's CIEDE2000 distance to every prototype by colour-science
    (`colour.delta_E`), then the achromatic rules."""
    import colour  # ~1 s to import

    pixels = _check_pixels(pixels)
    if len(pixels) == 0:
        return []
    lab = srgb_to_lab(pixels)
    lightness = lab[:, 0]
    chroma = np.hypot(lab[:, 1], lab[:, 2])
    proto_codes, proto_lab = _prototypes()
    codes = proto_codes[np.argmin(colour.delta_E(lab[:, None, :], proto_lab[None, :, :], method="CIE 2000"), axis=1)]
    gray = np.where(lightness < BLACK_BELOW_L, _BLACK, np.where(lightness > WHITE_ABOVE_L, _WHITE, _GRAY))
    codes = np.where(chroma < ACHROMATIC_CHROMA, gray, codes)
    codes = np.where((lightness < ALWAYS_BLACK_BELOW_L) & (chroma < DARK_HUE_MIN_CHROMA), _BLACK, codes)
    return [BASIC_COLORS[c] for c in codes.tolist()]


def _color_codes(pixels: np.ndarray) -> np.ndarray:
    """(n,) int64 index into BASIC_COLORS of each pixel's basic color term."""
    from monovoc_ros.core.evidence.quantize_kernels import nearest_ciede2000

    pixels = _check_pixels(pixels)
    if len(pixels) == 0:
        return np.zeros(0, np.int64)
    lab = srgb_to_lab(pixels)
    lightness = lab[:, 0]
    chroma = np.hypot(lab[:, 1], lab[:, 2])
    codes = np.where(lightness < BLACK_BELOW_L, _BLACK, np.where(lightness > WHITE_ABOVE_L, _WHITE, _GRAY))
    dark = (lightness < ALWAYS_BLACK_BELOW_L) & (chroma < DARK_HUE_MIN_CHROMA)
    codes[dark] = _BLACK
    # The nearest prototype (CIEDE2000, ties to the lower index: the palette quantization's numba kernel) only for
    # the pixels with a hue, once per distinct color: indoors most of an object's pixels are achromatic or repeat
    # (an object's 4096 pixels on office_0: 8.0 -> 2.7 ms; the object index names a color whenever an object's
    # views change).
    hued = np.flatnonzero((chroma >= ACHROMATIC_CHROMA) & ~dark)
    if hued.size:
        packed = (pixels[hued, 0].astype(np.int64) << 16) | (pixels[hued, 1].astype(np.int64) << 8) | pixels[hued, 2]
        _, first, inverse = np.unique(packed, return_index=True, return_inverse=True)
        proto_codes, proto_lab = _prototypes()
        lab_hued = np.ascontiguousarray(lab[hued[first]], np.float64)
        codes[hued] = proto_codes[nearest_ciede2000(lab_hued, np.ascontiguousarray(proto_lab, np.float64))[0]][inverse]
    return codes


def dominant_color_name(pixels: np.ndarray) -> str:
    """The most frequent basic color term among an object's pixels ((n, 3) sRGB uint8, e.g. all its mask
    pixels over all its views). Naming pixels and voting, rather than naming the mean color, keeps a
    two-colored object from averaging into a color it does not have."""
    pixels = _check_pixels(pixels)
    if len(pixels) == 0:
        raise ValueError("no pixels to name a color from")
    if len(pixels) > MAX_COLOR_PIXELS:
        pixels = pixels[np.linspace(0, len(pixels) - 1, MAX_COLOR_PIXELS).astype(np.int64)]
    counts = np.bincount(_color_codes(pixels), minlength=len(BASIC_COLORS))
    # Ties resolve in BASIC_COLORS order (argmax: the first largest) so the result never depends on set ordering.
    return BASIC_COLORS[int(np.argmax(counts))]


def masked_pixels(rgb: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The (n, 3) pixels of ``rgb`` under ``mask`` (resized nearest-neighbour if its resolution differs)."""
    from monovoc_ros.embed.crops import resize_mask

    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be an (H, W, 3) uint8 image, got shape {rgb.shape} dtype {rgb.dtype}")
    return rgb[resize_mask(mask, rgb.shape[0], rgb.shape[1])]


def _check_pixels(pixels: np.ndarray) -> np.ndarray:
    pixels = np.asarray(pixels)
    if pixels.ndim != 2 or pixels.shape[1] != 3 or pixels.dtype != np.uint8:
        raise ValueError(f"pixels must be an (n, 3) uint8 array, got shape {pixels.shape} dtype {pixels.dtype}")
    return pixels


def size_word(extent: Sequence[float]) -> str:
    """ "tiny", "small", "" (ordinary) or "large" from the object's largest extent in metres."""
    largest = float(np.max(_check_extent(extent)))
    return next(word for limit, word in _SIZE_WORDS if largest < limit)


def format_metres(value: float) -> str:
    """Two significant digits below 1 m (0.25, 0.04), one decimal above (1.2)."""
    if value < 1.0:
        return f"{value:.2g} m"
    return f"{value:.1f} m" if value < 10.0 else f"{value:.0f} m"


def _check_extent(extent: Sequence[float]) -> np.ndarray:
    extent = np.asarray(extent, dtype=np.float64)
    if extent.shape != (3,) or not np.all(np.isfinite(extent)) or np.any(extent < 0):
        raise ValueError(f"extent must be 3 finite non-negative sizes in metres, got {extent}")
    return extent


def clean_class_name(name: str) -> str:
    """A plain noun from a curated ImageNet name: "kite (bird of prey)" -> "kite",
    "cardboard box / carton" -> "cardboard box", "red wolf or maned wolf" -> "red wolf"."""
    name = re.sub(r"\s*\(.*?\)", "", name)
    name = re.split(r" / | or ", name)[0]
    return name.strip()


def describe(
    noun: str,
    *,
    color: str | None = None,
    extent: Sequence[float] | None = None,
    height_above_floor: float | None = None,
    up_axis: int = 2,
) -> str:
    """Compose e.g. "a red chair, 0.9 m tall" or "a small brown box, 0.2 m wide, 0.8 m above the floor".

    ``extent``: the object's axis-aligned size (m) in a frame whose ``up_axis`` points up; the phrase
    quotes its height when that is its largest horizontal-or-vertical size, else its width.
    ``height_above_floor``: the object's lowest point above the floor (m); omitted up to 0.15 m.
    """
    noun = " ".join(str(noun).split())
    if not noun:
        raise ValueError("describe needs a noun")
    if color is not None and color not in BASIC_COLORS:
        raise ValueError(f"unknown color {color!r}; expected one of {BASIC_COLORS}")
    words = []
    phrases = []
    if extent is not None:
        if up_axis not in (0, 1, 2):
            raise ValueError(f"up_axis must be 0, 1 or 2, got {up_axis}")
        ext = _check_extent(extent)
        if word := size_word(ext):
            words.append(word)
        height = float(ext[up_axis])
        width = float(np.max(np.delete(ext, up_axis)))
        phrases.append(f"{format_metres(height)} tall" if height >= width else f"{format_metres(width)} wide")
    if color is not None:
        words.append(color)
    words.append(noun)
    if height_above_floor is not None:
        if not np.isfinite(height_above_floor):
            raise ValueError(f"height_above_floor must be finite, got {height_above_floor}")
        if height_above_floor > ON_FLOOR_MAX_M:
            phrases.append(f"{format_metres(float(height_above_floor))} above the floor")
    article = "an" if words[0][0].lower() in "aeiou" else "a"
    return ", ".join([f"{article} {' '.join(words)}", *phrases])


def combine(image_emb: np.ndarray, text_emb: np.ndarray, weight: float = 0.5) -> np.ndarray:
    """Unit-norm ``(1 - weight) * image_emb + weight * text_emb`` (rows, or single vectors).

    ``weight`` is the share of the description; both inputs are renormalised first so it means the same
    whatever their norms."""
    image_emb = np.asarray(image_emb, dtype=np.float32)
    text_emb = np.asarray(text_emb, dtype=np.float32)
    if image_emb.shape != text_emb.shape:
        raise ValueError(f"image and text embeddings differ in shape: {image_emb.shape} vs {text_emb.shape}")
    if not 0.0 <= weight <= 1.0:
        raise ValueError(f"weight must be in [0, 1], got {weight}")
    mixed = (1.0 - weight) * l2_normalize(image_emb) + weight * l2_normalize(text_emb)
    return l2_normalize(mixed)


_VOCAB_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def class_vocabulary(backend) -> tuple[list[str], np.ndarray]:
    """ImageNet class names and their prompt embeddings in ``backend``'s space (cached per backend)."""
    names = getattr(backend, "class_names", None)
    embeddings = getattr(backend, "class_embeddings", None)
    if names is not None and embeddings is not None:
        return list(names), np.asarray(embeddings, dtype=np.float32)
    if backend not in _VOCAB_CACHE:
        from monovoc_ros.embed import conse_files as cf

        names = cf.parse_class_names(cf.packaged_class_names_text())
        _VOCAB_CACHE[backend] = (names, backend.embed_texts([cf.CLASS_PROMPT.format(n) for n in names]))
    return _VOCAB_CACHE[backend]


def best_class_name(image_emb: np.ndarray, backend) -> str:
    """The noun for a description when no label is given: the ImageNet class whose prompt embedding is
    closest to the object's image embedding, cleaned to a plain noun."""
    names, embeddings = class_vocabulary(backend)
    image_emb = np.asarray(image_emb, dtype=np.float32).reshape(-1)
    if image_emb.shape[0] != embeddings.shape[1]:
        raise ValueError(f"embedding has dim {image_emb.shape[0]}, backend space has {embeddings.shape[1]}")
    return clean_class_name(names[int(np.argmax(embeddings @ image_emb))])
