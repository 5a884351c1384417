"""The torch rasterizer: the same definition as reference.py, vectorized per tile, on CPU or CUDA tensors.

Formulation (dense per tile): every Gaussian-tile pair of the radius-box footprint is listed, pairs
are sorted by (tile, depth rank), and tiles are processed in chunks of similar list length as dense
(tiles, 256 pixels, K Gaussians) tensors. Front-to-back compositing is a cumulative product along K;
the termination rule is a mask on it: a pixel stops at the first Gaussian whose next transmittance
would fall below T_MIN, and because the running product never increases, every later Gaussian is
masked too. Projection runs in float64 (as the numba kernel does), compositing in float32 (as the
CUDA rasterizers do). Nothing here is device-specific: the same code runs on "cpu" and "cuda".
"""

from __future__ import annotations

import threading
import weakref

import numpy as np
import torch

from monovoc_ros.core.map.gaussians import GaussianMap
from monovoc_ros.core.raster.constants import (
    ALPHA_MAX,
    ALPHA_MIN,
    COV2D_DILATION,
    DEPTH_MIN_COVERAGE,
    EIGEN_FLOOR,
    NEAR_PLANE,
    RADIUS_SIGMAS,
    T_MIN,
    TILE,
)
from monovoc_ros.core.raster.inputs import View
from monovoc_ros.core.raster.projection import jacobian_limits, tile_grid
from monovoc_ros.core.raster.vote_tables import TILE_CHANNELS

_PIXELS = TILE * TILE
# Elements of one (tiles x pixels x Gaussians) chunk tensor; several such tensors are alive at once.
CHUNK_ELEMENTS = {"cpu": 1 << 22, "cuda": 1 << 25}

_CACHE_LOCK = threading.Lock()
_MAP_TENSORS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def resolve_device(device: str | None) -> torch.device:
    try:
        dev = torch.device("cpu" if device is None else device)
    except (RuntimeError, TypeError) as exc:
        raise ValueError(f"device: {device!r} is not a torch device ({exc})") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r} requested but torch.cuda.is_available() is False")
    return dev


def _map_tensors(gmap: GaussianMap, dev: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Means and covariances (float64) and opacities (float32) on `dev`, uploaded once per map."""
    with _CACHE_LOCK:
        per_map = _MAP_TENSORS.setdefault(gmap, {})
        key = str(dev)
        if key not in per_map:
            per_map[key] = (
                torch.from_numpy(gmap.means.astype(np.float64)).to(dev),
                torch.from_numpy(gmap.covariances.astype(np.float64)).to(dev),
                torch.from_numpy(gmap.opacities.copy()).to(dev),
            )
        return per_map[key]


def _project(means: torch.Tensor, cov6: torch.Tensor, view: View) -> dict[str, torch.Tensor]:
    k = view.intrinsics
    dev = means.device
    w2c = torch.as_tensor(view.world_to_cam, dtype=torch.float64, device=dev)
    R, t = w2c[:3, :3], w2c[:3, 3]
    cam = means @ R.T + t
    x, y, z = cam[:, 0], cam[:, 1], cam[:, 2]
    front = torch.isfinite(cam).all(dim=1) & (z >= NEAR_PLANE) & (z <= view.far)
    zs = torch.where(front, z, torch.ones_like(z))
    lim_xn, lim_xp, lim_yn, lim_yp = jacobian_limits(view)
    xz = (x / zs).clamp(-lim_xn, lim_xp)
    yz = (y / zs).clamp(-lim_yn, lim_yp)
    n = means.shape[0]
    J = torch.zeros((n, 2, 3), dtype=torch.float64, device=dev)
    J[:, 0, 0] = k.fx / zs
    J[:, 0, 2] = -k.fx * xz / zs
    J[:, 1, 1] = k.fy / zs
    J[:, 1, 2] = -k.fy * yz / zs
    M = J @ R
    cov = cov6[:, [0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(n, 3, 3)
    cov2 = M @ cov @ M.transpose(1, 2)
    a = cov2[:, 0, 0] + COV2D_DILATION
    b = cov2[:, 0, 1]
    cc = cov2[:, 1, 1] + COV2D_DILATION
    det = a * cc - b * b
    front &= torch.isfinite(det) & (det > 0)
    det = torch.where(front, det, torch.ones_like(det))
    mid = 0.5 * (a + cc)
    lam = mid + torch.sqrt(torch.clamp(mid * mid - det, min=EIGEN_FLOOR))
    radius = torch.where(front, torch.ceil(RADIUS_SIGMAS * torch.sqrt(torch.where(front, lam, 0.0))), 0.0)
    u = torch.where(front, k.fx * x / zs + k.cx, 0.0)
    v = torch.where(front, k.fy * y / zs + k.cy, 0.0)
    gx, gy = tile_grid(k.width, k.height)
    rect = torch.stack(
        [
            torch.floor((u - radius) / TILE).clamp(0, gx),
            torch.floor((u + radius + TILE - 1) / TILE).clamp(0, gx),
            torch.floor((v - radius) / TILE).clamp(0, gy),
            torch.floor((v + radius + TILE - 1) / TILE).clamp(0, gy),
        ],
        dim=1,
    )
    rect = torch.where(front[:, None], torch.nan_to_num(rect), 0.0).to(torch.int64)
    visible = front & (rect[:, 1] > rect[:, 0]) & (rect[:, 3] > rect[:, 2])
    return {
        "u": u.float(),
        "v": v.float(),
        # The conic factored as q(d) = A (dx + R dy)^2 + S dy^2, accurate in float32 (numba_kernels.py).
        "conic": torch.stack([cc / det, -b / cc, 1.0 / cc], dim=1).float(),
        "depth": z.float(),
        "rect": rect,
        "visible": visible,
    }


class _Pairs:
    """Gaussian-tile pairs of the visible Gaussians, sorted by tile and then front to back."""

    def __init__(self, proj: dict[str, torch.Tensor], opacities: torch.Tensor, n_tiles: int, gx: int):
        dev = opacities.device
        vis = torch.nonzero(proj["visible"]).squeeze(1)
        # Stable sort on float32 depth: equal depths keep map order, as in the numba kernel.
        _, by_depth = torch.sort(proj["depth"][vis], stable=True)
        self.index = vis[by_depth]  # map index of each depth rank
        g = self.index
        self.u, self.v = proj["u"][g], proj["v"][g]
        self.A, self.R, self.S = proj["conic"][g].unbind(1)
        self.o = opacities[g]
        self.z = proj["depth"][g]
        x0, x1, y0, y1 = proj["rect"][g].unbind(1)
        width = x1 - x0
        counts = width * (y1 - y0)
        rank = torch.repeat_interleave(torch.arange(len(g), device=dev), counts)
        first = torch.cumsum(counts, 0) - counts
        local = torch.arange(len(rank), device=dev) - first[rank]
        tile = (y0[rank] + local // width[rank]) * gx + x0[rank] + local % width[rank]
        _, order = torch.sort(tile * max(len(g), 1) + rank)
        self.rank = rank[order]  # depth rank of each pair, tiles in order, front to back within a tile
        self.tile_count = torch.bincount(tile, minlength=n_tiles)
        self.tile_start = torch.cumsum(self.tile_count, 0) - self.tile_count


def _tile_layout(image: torch.Tensor, gx: int, gy: int) -> torch.Tensor:
    """(H, W, C) -> (tiles, 256, C), zero-padded at the right and bottom borders."""
    h, w, ch = image.shape
    padded = torch.zeros((gy * TILE, gx * TILE, ch), dtype=image.dtype, device=image.device)
    padded[:h, :w] = image
    return padded.reshape(gy, TILE, gx, TILE, ch).permute(0, 2, 1, 3, 4).reshape(gy * gx, _PIXELS, ch)


def _chunks(tile_count: torch.Tensor, budget: int):
    """Non-empty tiles, longest list first, grouped so that tiles x 256 x longest list <= budget."""
    counts, tiles = torch.sort(tile_count, descending=True, stable=True)
    counts_host = counts.cpu().numpy()
    nonempty = int((counts_host > 0).sum())
    start = 0
    while start < nonempty:
        k = int(counts_host[start])
        n = max(1, min(nonempty - start, budget // (_PIXELS * k)))
        yield tiles[start : start + n], k
        start += n


def _composite(pairs: _Pairs, tiles: torch.Tensor, k: int, gx: int) -> tuple[torch.Tensor, ...]:
    """Weights (n, 256, k), final transmittance (n, 256), pair ranks (n, k) and pair mask of a chunk."""
    dev = tiles.device
    slot = torch.arange(k, device=dev)
    in_list = slot[None, :] < pairs.tile_count[tiles][:, None]
    rank = pairs.rank[torch.where(in_list, pairs.tile_start[tiles][:, None] + slot[None, :], 0)]
    pix = torch.arange(_PIXELS, device=dev)
    px = ((tiles % gx) * TILE)[:, None].float() + (pix % TILE).float()[None, :]
    py = ((tiles // gx) * TILE)[:, None].float() + (pix // TILE).float()[None, :]
    dx = px[:, :, None] - pairs.u[rank][:, None, :]
    dy = py[:, :, None] - pairs.v[rank][:, None, :]
    t = dx + pairs.R[rank][:, None, :] * dy
    power = -0.5 * (pairs.A[rank][:, None, :] * t * t + pairs.S[rank][:, None, :] * dy * dy)
    del dx, dy, t
    alpha = torch.clamp(pairs.o[rank][:, None, :] * torch.exp(power), max=ALPHA_MAX)
    alpha = torch.where((alpha >= ALPHA_MIN) & (power <= 0) & in_list[:, None, :], alpha, 0.0)
    del power
    after = torch.cumprod(1.0 - alpha, dim=2)
    before = torch.cat([torch.ones_like(after[:, :, :1]), after[:, :, :-1]], dim=2)
    blends = after >= T_MIN
    weights = torch.where(blends, alpha * before, 0.0)
    final_T = torch.where(blends, after, 1.0).amin(dim=2)
    return weights, final_T, rank, in_list


def _prepare(gmap: GaussianMap, view: View, device: str | None):
    dev = resolve_device(device)
    means, cov6, opac = _map_tensors(gmap, dev)
    proj = _project(means, cov6, view)
    gx, gy = tile_grid(view.width, view.height)
    return dev, _Pairs(proj, opac, gx * gy, gx), gx, gy, CHUNK_ELEMENTS.get(dev.type, CHUNK_ELEMENTS["cuda"])


@torch.no_grad()
def accumulate(
    gmap: GaussianMap,
    mask: np.ndarray,
    view: View,
    valid: np.ndarray | None,
    background: np.ndarray | None,
    weight_power: int = 1,
    device: str | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    n = len(gmap)
    if n == 0:
        resolve_device(device)
        return np.zeros((n, 3)), np.zeros(n), 0
    dev, pairs, gx, gy, budget = _prepare(gmap, view, device)
    nv = len(pairs.index)
    obs = torch.tensor(mask, device=dev).float()
    if mask.dtype == np.uint8:
        obs = obs / 255.0
    keep = torch.ones(mask.shape[:2], device=dev) if valid is None else torch.tensor(valid, device=dev).float()
    obs_t = _tile_layout(obs, gx, gy)
    keep_t = _tile_layout(keep[:, :, None], gx, gy)[:, :, 0]
    bg = None if background is None else torch.as_tensor(background, dtype=torch.float32, device=dev)
    color_sum = torch.zeros((nv, 3), dtype=torch.float64, device=dev)
    weight_sum = torch.zeros(nv, dtype=torch.float64, device=dev)
    for tiles, k in _chunks(pairs.tile_count, budget):
        weights, final_T, rank, in_list = _composite(pairs, tiles, k, gx)
        y = obs_t[tiles]
        if bg is not None:
            y = y - final_T[:, :, None] * bg
        weights = (weights * keep_t[tiles][:, :, None]) ** weight_power
        w_pair = weights.sum(dim=1)
        c_pair = torch.bmm(weights.transpose(1, 2), y)
        weight_sum.index_add_(0, rank[in_list], w_pair[in_list].double())
        color_sum.index_add_(0, rank[in_list], c_pair[in_list].double())
    out_c = np.zeros((n, 3))
    out_w = np.zeros(n)
    index = pairs.index.cpu().numpy()
    out_c[index] = color_sum.cpu().numpy()
    out_w[index] = weight_sum.cpu().numpy()
    return out_c, out_w, nv


@torch.no_grad()
def accumulate_votes(
    gmap: GaussianMap, labels: np.ndarray, view: View, weight_power: int, slots: int, device: str | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """Vote evidence (see vote_tables) with the tile channels as one-hot observations."""
    from monovoc_ros.core.raster.numba_impl import tile_slots  # tested against vote_tables' plain twin

    n = len(gmap)
    if n == 0:
        resolve_device(device)
        return np.zeros(0, np.int64), np.zeros((0, slots), np.int32), np.zeros((0, slots)), np.zeros(0), 0
    dev, pairs, gx, gy, budget = _prepare(gmap, view, device)
    nv = len(pairs.index)
    slot_map, table = tile_slots(labels, view.width, view.height)  # the shared tile rule (vote_tables)
    n_labels = max(int(labels.max()) + 1 if labels.size else 0, 1)
    slot_t = torch.tensor(slot_map.astype(np.int64), device=dev)
    onehot = (slot_t[:, :, None] == torch.arange(TILE_CHANNELS, device=dev)[None, None, :]).float()
    obs_t = _tile_layout(onehot, gx, gy)
    # Column n_labels collects a crowded tile's pooled channel (and never-used channels, which get no weight).
    table_t = torch.tensor(np.where(table >= 0, table, n_labels).astype(np.int64), device=dev)
    dense = torch.zeros(nv * (n_labels + 1), dtype=torch.float64, device=dev)
    for tiles, k in _chunks(pairs.tile_count, budget):
        weights, _, rank, in_list = _composite(pairs, tiles, k, gx)
        v_pair = torch.bmm((weights**weight_power).transpose(1, 2), obs_t[tiles])  # (n, k, 4)
        column = table_t[tiles][:, None, :].expand(-1, k, -1)
        key = rank[:, :, None] * (n_labels + 1) + column
        dense.index_add_(0, key[in_list].reshape(-1), v_pair[in_list].reshape(-1).double())
    dense = dense.reshape(nv, n_labels + 1)
    named = dense[:, :n_labels]
    # The heaviest labels on the device; only (V, slots) arrays travel back.
    kept, index = torch.topk(named, min(slots, n_labels), dim=1)
    rest = torch.clamp(named.sum(dim=1) - kept.sum(dim=1), min=0.0) + dense[:, n_labels]
    top_weights = np.zeros((nv, slots))
    top_labels = np.full((nv, slots), -1, np.int32)
    kept_np, index_np = kept.cpu().numpy(), index.cpu().numpy()
    top_weights[:, : kept_np.shape[1]] = np.where(kept_np > 0, kept_np, 0.0)
    top_labels[:, : kept_np.shape[1]] = np.where(kept_np > 0, index_np, -1)
    rest = rest.cpu().numpy()
    return pairs.index.cpu().numpy().astype(np.int64), top_labels, top_weights, rest, nv


@torch.no_grad()
def render(
    gmap: GaussianMap, colors: np.ndarray, view: View, background: np.ndarray | None, device: str | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    h, w = view.height, view.width
    if len(gmap) == 0:
        resolve_device(device)
        bg = np.zeros(3, np.float32) if background is None else background
        return np.broadcast_to(bg, (h, w, 3)).copy(), np.ones((h, w), np.float32), np.zeros((h, w), np.float32)
    dev, pairs, gx, gy, budget = _prepare(gmap, view, device)
    color = torch.tensor(colors, device=dev)[pairs.index]
    image_t = torch.zeros((gx * gy, _PIXELS, 3), device=dev)
    trans_t = torch.ones((gx * gy, _PIXELS), device=dev)
    depth_t = torch.zeros((gx * gy, _PIXELS), device=dev)
    for tiles, k in _chunks(pairs.tile_count, budget):
        weights, final_T, rank, _ = _composite(pairs, tiles, k, gx)
        image_t[tiles] = torch.bmm(weights, color[rank])
        depth_sum = torch.bmm(weights, pairs.z[rank][:, :, None])[:, :, 0]
        cover = 1.0 - final_T
        depth_t[tiles] = torch.where(cover > DEPTH_MIN_COVERAGE, depth_sum / torch.where(cover > 0, cover, 1.0), 0.0)
        trans_t[tiles] = final_T
    if background is not None:
        image_t += trans_t[:, :, None] * torch.as_tensor(background, dtype=torch.float32, device=dev)

    def untile(t: torch.Tensor) -> np.ndarray:
        ch = t.shape[2] if t.ndim == 3 else 1
        full = t.reshape(gy, gx, TILE, TILE, ch).permute(0, 2, 1, 3, 4).reshape(gy * TILE, gx * TILE, ch)
        return full[:h, :w].squeeze(2).cpu().numpy() if ch == 1 else full[:h, :w].cpu().numpy()

    return untile(image_t), untile(trans_t), untile(depth_t)
