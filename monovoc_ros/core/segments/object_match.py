"""Object ids that survive a rebuild: the objects of a re-integrated state matched to the ones it replaces.

With per-frame mask ids (core.segments.association) object ids are issued by the association, keyframe by
keyframe. A re-integration (core.follow.map_updater) associates the logged segments again from scratch, so
the rebuilt state names the same objects with ids of its own; everything downstream (the object database's
views and embeddings, query answers, the semantic cloud) knows the old ones. Both states label the same
Gaussian map, so each rebuilt object is matched to the old object holding most of its Gaussians, one to one,
and takes its id (`match_objects`); the rest get ids the old association never issued
(Associator.adopt_ids), so that no id ever comes to stand for another object.
"""

from __future__ import annotations

import numpy as np

from monovoc_ros.core.evidence.palette import UNOBSERVED_ID

# A rebuilt object and an old one are the same object when the Gaussians both hold are at least this share of
# the smaller of the two (one lies mostly inside the other): a rebuild that split an old object gives its id
# to the larger part, one that fused two gives it the larger old object's id.
MIN_SHARE = 0.5


def match_objects(old_ids: np.ndarray, new_ids: np.ndarray, min_share: float = MIN_SHARE) -> dict[int, int]:
    """Rebuilt object id -> old object id, one to one: pairs of objects taken greedily by the number of
    Gaussians both hold, largest first, each pair kept when that number is at least `min_share` of the
    smaller object's Gaussians. `old_ids`, `new_ids`: (N,) uint32 object id per Gaussian of one map
    (UNOBSERVED_ID where unlabelled). Greedy rather than Hungarian: the overlaps are sparse (a few pairs per
    object) and the map may hold thousands of objects; where one object's overlap dominates, as here, both
    give the same pairs."""
    old_ids = np.asarray(old_ids, np.uint32)
    new_ids = np.asarray(new_ids, np.uint32)
    if old_ids.shape != new_ids.shape:
        raise ValueError(f"match_objects: labels of different maps ({old_ids.shape} vs {new_ids.shape})")
    old_known, new_known = old_ids != UNOBSERVED_ID, new_ids != UNOBSERVED_ID
    both = old_known & new_known
    if not both.any():
        return {}
    old_objects, old_sizes = np.unique(old_ids[old_known], return_counts=True)
    new_objects, new_sizes = np.unique(new_ids[new_known], return_counts=True)
    old_size = dict(zip(old_objects.tolist(), old_sizes.tolist(), strict=True))
    new_size = dict(zip(new_objects.tolist(), new_sizes.tolist(), strict=True))
    keys = (new_ids[both].astype(np.uint64) << np.uint64(32)) | old_ids[both].astype(np.uint64)
    pairs, counts = np.unique(keys, return_counts=True)  # (P,) the (new, old) pairs and their shared Gaussians
    order = np.lexsort((pairs, -counts))  # most shared first; ties by ids, so the result is deterministic
    matches: dict[int, int] = {}
    taken: set[int] = set()
    for key, count in zip(pairs[order].tolist(), counts[order].tolist(), strict=True):
        new, old = key >> 32, key & 0xFFFFFFFF
        if new in matches or old in taken:
            continue
        if count >= min_share * min(new_size[new], old_size[old]):
            matches[new] = old
            taken.add(old)
    return matches
