"""What a keyframe adds per Gaussian: the vote state (``votes``, ``vote_kernels``), the SCD accumulators
(``state``), mask pixels to objects (``pixel_labels``), object ids and the palette of the masks (``palette``,
``palette_kernels``), palette quantization (``quantize``, ``quantize_kernels``) and sRGB to CIELAB (``color``).

May import ``core.map`` and ``core.raster``.
"""
