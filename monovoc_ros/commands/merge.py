"""`monovoc merge SNAP_A SNAP_B -o OUT`: one map from two maps of the same Gaussian map (two bags, two robots)."""

from __future__ import annotations

import argparse
import json

from monovoc_ros.core.map_store import MapStoreError, load_snapshot, save_snapshot


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "merge",
        help="merge two saved maps of the same Gaussian map into one",
        description="Adds the evidence (votes or SCD sums) and palette counts of two map directories built "
        "with the same settings on the same Gaussian map, e.g. two halves of a bag or two robots; the "
        "result equals mapping all their keyframes at once. Keyframes present in both are refused.",
    )
    p.add_argument("first", help="map directory (monovoc map -o, or the node's map_directory)")
    p.add_argument("second", help="map directory")
    p.add_argument("-o", "--out", required=True, help="map directory to write")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        first, second = load_snapshot(args.first), load_snapshot(args.second)
        merged = first.merged(second)
    except (MapStoreError, ValueError) as exc:
        raise SystemExit(f"monovoc merge: {exc}") from None
    info = save_snapshot(merged, args.out)
    summary = {
        "snapshot": str(info.path),
        "keyframes": merged.n_keyframes,
        "gaussians": len(merged.gaussians),
        "observed_gaussians": int(merged.result().observed.sum()),
    }
    print(json.dumps(summary, indent=1))
    return 0
