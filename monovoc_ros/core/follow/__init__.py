"""Following the SLAM's map: how it moved (``map_motion``), which old Gaussian's evidence each new one
takes (``map_follow``, ``map_follow_kernels``) and the keyframe log kept for re-integration (``keyframe_log``).

May import ``core.map``, ``core.raster``, ``core.evidence``, ``core.segments`` and the root's ``keyframe``.
"""
