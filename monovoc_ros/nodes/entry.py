"""The nodes' console scripts (setup.py): each imports its node only when run, so that a Ctrl-C, or the SIGINT a
launch sends when it stops early (a bag that cannot be replayed), during the second its imports take ends the
process as a stop during the node's start-up does (one line, exit code 0: nothing was written) instead of with a
KeyboardInterrupt traceback from deep inside an import."""

from __future__ import annotations

import importlib
import sys


def _run(module: str) -> int:
    try:
        main = importlib.import_module(module).main
    except KeyboardInterrupt:
        name = module.rsplit(".", 1)[-1]
        print(f"{name}: stop requested during start-up (importing): exiting, nothing written", file=sys.stderr)
        return 0
    return main()


def semantic_mapper() -> int:
    """`semantic_mapper`: mapping, object database and text queries (monovoc_ros.nodes.semantic_mapper)."""
    return _run("monovoc_ros.nodes.semantic_mapper")


def mapping_node() -> int:
    """`mapping_node`: the mapping node alone (monovoc_ros.nodes.mapping_node)."""
    return _run("monovoc_ros.nodes.mapping_node")


def segmenter() -> int:
    """`segmenter`: keyframe images to per-frame masks and class names (monovoc_ros.nodes.segmenter)."""
    return _run("monovoc_ros.nodes.segmenter")
