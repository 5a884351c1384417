"""The plain definitions behind vote evidence (METHOD.md section 8), shared by every implementation.

A keyframe's pixels carry object labels (int32, -1 = no evidence). Per 16x16 tile the kernels keep
four vote channels: a tile showing at most four labels gives each its own channel; a crowded tile
keeps its three largest labels (pixel count descending, then label) and pools the rest in channel 3
as "other" (`OTHER_LABEL`), so the per-pair cost of voting equals the SCD kernel's four sums. Per
Gaussian the votes of its pairs are summed per label and the `slots` heaviest labels are kept
(weight descending, then label); the rest joins "other". Both rules are exact whenever a tile shows
at most four labels and a Gaussian collects at most `slots` labels in one keyframe.
"""

from __future__ import annotations

import numpy as np

from monovoc_ros.core.raster.constants import TILE
from monovoc_ros.core.raster.projection import tile_grid

TILE_CHANNELS = 4
OTHER_LABEL = -2  # tile channel pooling the labels of a crowded tile
UNUSED_LABEL = -1


def tile_slots_reference(labels: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) int8 channel of every pixel (-1 where label < 0) and the (tiles, 4) int32 label of each
    tile channel (UNUSED_LABEL, or OTHER_LABEL for a crowded tile's pooled channel)."""
    labels = np.asarray(labels, np.int32)
    gx, gy = tile_grid(width, height)
    slot_map = np.full((height, width), -1, np.int8)
    table = np.full((gx * gy, TILE_CHANNELS), UNUSED_LABEL, np.int32)
    for t in range(gx * gy):
        ys = slice((t // gx) * TILE, (t // gx) * TILE + TILE)
        xs = slice((t % gx) * TILE, (t % gx) * TILE + TILE)
        block = labels[ys, xs]
        found, counts = np.unique(block[block >= 0], return_counts=True)
        ranked = found[np.lexsort((found, -counts))]
        kept = ranked if ranked.size <= TILE_CHANNELS else ranked[: TILE_CHANNELS - 1]
        table[t, : kept.size] = kept
        if ranked.size > TILE_CHANNELS:
            table[t, TILE_CHANNELS - 1] = OTHER_LABEL
        channel = np.full(block.shape, -1, np.int8)
        for c, lab in enumerate(kept):
            channel[block == lab] = c
        if ranked.size > TILE_CHANNELS:
            channel[(block >= 0) & (channel < 0)] = TILE_CHANNELS - 1
        slot_map[ys, xs] = channel
    return slot_map, table


def pixel_vote_labels(slot_map: np.ndarray, table: np.ndarray, width: int) -> np.ndarray:
    """(H, W) int32 label each pixel votes for: its channel's label (OTHER_LABEL when pooled), -1 for none."""
    h, w = slot_map.shape
    gx = (width + TILE - 1) // TILE
    ys, xs = np.mgrid[0:h, 0:w]
    tiles = (ys // TILE) * gx + xs // TILE
    out = table[tiles, np.maximum(slot_map, 0)]
    return np.where(slot_map >= 0, out, -1).astype(np.int32)


def top_entries(dense: np.ndarray, other: np.ndarray, slots: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """From per-label votes (V, L) float64 and pooled votes (V,): the `slots` heaviest labels (int32,
    -1 where fewer), their votes, and "other" = pooled + the rest."""
    v, n_labels = dense.shape
    order = np.lexsort((np.broadcast_to(np.arange(n_labels), dense.shape), -dense), axis=1)[:, :slots]
    weights = np.take_along_axis(dense, order, axis=1)
    labels = np.where(weights > 0, order, -1).astype(np.int32)
    weights = np.where(weights > 0, weights, 0.0)
    if order.shape[1] < slots:
        pad = slots - order.shape[1]
        labels = np.pad(labels, ((0, 0), (0, pad)), constant_values=-1)
        weights = np.pad(weights, ((0, 0), (0, pad)))
    rest = dense.sum(axis=1) - weights.sum(axis=1)
    return labels, weights, other + np.maximum(rest, 0.0)
