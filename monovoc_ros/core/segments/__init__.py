"""Masks numbered per frame and segmenters' names: per-frame segments associated with map objects
(``association``), the map's labels rendered in one pass (``label_render``, ``label_render_kernels``),
segmenters' class names (``segment_labels``), one label per object (``object_labels``) and what a real
segmenter does to masks (``segment_noise``).

May import ``core.map``, ``core.raster``, ``core.evidence`` and the root's ``keyframe``.
"""
