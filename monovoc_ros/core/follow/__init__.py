"""Following the SLAM's map: how it moved (``map_motion``), which old Gaussian's evidence each new one
takes (``map_follow``, ``map_follow_kernels``), the keyframe log kept for re-integration (``keyframe_log``),
and the one owner of map updates and corrected poses (``map_updater``: refusals, the evidence carried over,
the logged poses, re-integration).

May import ``core.map``, ``core.raster``, ``core.evidence``, ``core.segments`` and the root's ``keyframe``.
"""
