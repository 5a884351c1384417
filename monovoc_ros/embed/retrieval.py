"""Ranking objects for text queries and the paper's retrieval metrics (top-k accuracy of text queries)."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

from monovoc_ros.embed.arrays import l2_normalize


def rank(text_embs: np.ndarray, object_embs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cosine-rank objects for each query.

    ``text_embs`` (Q, D), ``object_embs`` (M, D); rows are normalised here, so any norms are fine.
    Returns ``(indices, scores)``, both (Q, M): object indices best first and their cosine scores in
    the same order. Ties keep the lower object index first (stable sort).
    """
    text_embs = np.asarray(text_embs, dtype=np.float32)
    object_embs = np.asarray(object_embs, dtype=np.float32)
    if text_embs.ndim != 2 or object_embs.ndim != 2:
        raise ValueError(f"expected 2-D arrays, got {text_embs.shape} and {object_embs.shape}")
    if text_embs.shape[1] != object_embs.shape[1]:
        raise ValueError(f"dimension mismatch: queries have {text_embs.shape[1]}, objects {object_embs.shape[1]}")
    similarity = l2_normalize(text_embs) @ l2_normalize(object_embs).T
    indices = np.argsort(-similarity, axis=1, kind="stable")
    return indices, np.take_along_axis(similarity, indices, axis=1)


def topk_accuracy(
    rankings: np.ndarray | Sequence[Sequence[int]],
    expected: Sequence[Iterable[int]],
    ks: Sequence[int] = (1, 3),
) -> dict[str, float]:
    """Share of queries with an expected object among their first k results, for each k in ``ks``.

    ``rankings`` (Q, M) as returned by :func:`rank`; ``expected[q]`` the set of correct object indices
    for query q (several when a query names a class with several instances). Returns
    ``{"top1": ..., "top3": ..., "mrr": ..., "n_queries": Q}``; ``mrr`` is the mean reciprocal rank of the
    first correct object.
    """
    rankings = np.asarray(rankings)
    expected = [set(int(i) for i in e) for e in expected]
    if rankings.ndim != 2:
        raise ValueError(f"rankings must be (Q, M), got shape {rankings.shape}")
    if len(expected) != rankings.shape[0]:
        raise ValueError(f"{rankings.shape[0]} rankings but {len(expected)} expected sets")
    if rankings.shape[0] == 0:
        raise ValueError("no queries to score")
    if any(not e for e in expected):
        raise ValueError("every query needs at least one expected object")
    n_objects = rankings.shape[1]
    if any(not 0 <= i < n_objects for e in expected for i in e):
        raise ValueError(f"expected object index outside [0, {n_objects})")
    if any(int(k) < 1 for k in ks):
        raise ValueError(f"k must be >= 1, got {list(ks)}")
    first_hit = np.array([_first_hit(row, e) for row, e in zip(rankings, expected, strict=True)])
    result: dict[str, float] = {f"top{int(k)}": float(np.mean(first_hit < int(k))) for k in ks}
    result["mrr"] = float(np.mean(1.0 / (first_hit + 1)))
    result["n_queries"] = int(rankings.shape[0])
    return result


def chance_topk(n_objects: int, n_expected: int, k: int) -> float:
    """Expected top-k accuracy of a uniformly random ranking: 1 - C(M - E, k) / C(M, k)."""
    if not 1 <= n_expected <= n_objects or k < 1:
        raise ValueError(f"need 1 <= n_expected <= n_objects and k >= 1, got {n_expected}, {n_objects}, {k}")
    return 1.0 - math.comb(n_objects - n_expected, k) / math.comb(n_objects, k)


def _first_hit(row: np.ndarray, expected: set[int]) -> int:
    hits = np.flatnonzero(np.isin(row, list(expected)))
    if hits.size == 0:
        raise ValueError("a ranking does not contain its expected object")
    return int(hits[0])
