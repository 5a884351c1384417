"""`monovoc warm-up`: compiles the numba kernels into their on-disk cache, so that no node waits for them."""

from __future__ import annotations

import argparse
import json


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "warm-up",
        help="compile the mapping and object kernels into numba's cache (once per install)",
        description="Runs every mapping path (votes, per-frame ids, SCD), a map update and the object views "
        "once on a tiny scene, so that numba compiles their kernels into its on-disk cache (~20-40 s on 2 cores "
        "the first time, ~1 s once cached). scripts/install.sh runs it; after a colcon build run it from the "
        "install space. A node that finds the cache empty runs this in a child process before it subscribes.",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from monovoc_ros.core.warm_up import kernels_cached, warm_up_all
    from monovoc_ros.objects.views import warm_up_views

    cached = kernels_cached()
    seconds = warm_up_all() + warm_up_views()
    print(json.dumps({"kernels_cached_before": cached, "seconds": round(seconds, 2)}), flush=True)
    return 0
