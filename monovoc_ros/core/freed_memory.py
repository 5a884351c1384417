"""Freed memory kept for the next block of its size (glibc), not given back to the system.

A map message at robot scale passes through several buffers of its own size, each allocated and freed per
message: Fast DDS's reassembly of its fragments, rmw's serialized message, the Python bytes of a raw take (57 MB
each for a 1M-Gaussian map). glibc maps every block over its mmap threshold (at most 32 MB) afresh and unmaps it
when it is freed, so every page of the next one faults on its first touch: on the development VM copying 57 MB
into a fresh block took 45 ms, into a reused one 5 ms, and a subscriber's take and decoding of a 1M map cost
295-593 core-ms against 81-109 with freed blocks kept (docs/results.md, twenty-fifth session).

`keep_freed_memory` has glibc serve blocks from its heaps instead of mappings of their own (M_MMAP_MAX 0; a thread
other than the main one still gets a mapping for a block over 64 MiB, its heaps' size) and trim a heap only once
1 GiB of it is free at its top (M_TRIM_THRESHOLD): a process's resident memory then stays near its peak (it did
not grow over 40 maps). A user's own MALLOC_MMAP_MAX_, MALLOC_TRIM_THRESHOLD_, MALLOC_MMAP_THRESHOLD_ or the same
glibc.malloc tunables are left as they are; without glibc's `mallopt` (another C library) nothing changes.

For the map reader process only (nodes/map_reader.py), which copies and decodes maps. Not for the mapping node: there
numpy's big arrays, taken from the heap instead of fresh mappings, lose the transparent huge pages numpy asks the
kernel for, and the rasterizer's passes over them slow down (1M fast runs, two pairs: integration 101-103 ->
116-117 ms a keyframe, 6.05-6.31 -> 4.95-5.35 keyframes/s).
"""

from __future__ import annotations

import ctypes
import os

# mallopt's parameters (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
_TRIM_THRESHOLD_BYTES = 1 << 30
_USER_SETTINGS = ("MALLOC_MMAP_MAX_", "MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_")
_USER_TUNABLES = ("glibc.malloc.mmap_max", "glibc.malloc.trim_threshold", "glibc.malloc.mmap_threshold")


def keep_freed_memory() -> bool:
    """Sets glibc's allocator for this process as the module docstring says; returns whether it did (False: the
    user set it, or this C library has no mallopt). Call it early: blocks mapped before keep their mappings."""
    tunables = os.environ.get("GLIBC_TUNABLES", "")
    if any(os.environ.get(name) for name in _USER_SETTINGS) or any(name in tunables for name in _USER_TUNABLES):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the C library the interpreter runs on
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    # The trim threshold first: without it, heaps without mappings would still give freed memory back.
    return bool(mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD_BYTES)) and bool(mallopt(_M_MMAP_MAX, 0))
