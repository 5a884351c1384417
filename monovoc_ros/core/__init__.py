"""The ROS-free core, grouped by the method's stages (docs/architecture.md), in import order:

- ``map/``: the SLAM's geometry (the Gaussian map, PLY files, cameras and poses);
- ``raster/``: the rasterizer (evidence sums, votes and rendering, three implementations);
- ``evidence/``: what a keyframe adds per Gaussian (votes, the SCD state, pixel labels, palettes, quantization);
- ``segments/``: masks numbered per frame and segmenters' names (association, label rendering, object labels);
- ``follow/``: following the SLAM's map (its motion, the evidence each new Gaussian takes, the keyframe log);
- ``evaluation/``: scoring and the dataset readers.

A stage imports from itself and from the stages listed before it, never from one after it. At the root:
``thread_pools`` (idle thread pools sleep), ``freed_memory`` (glibc keeps freed blocks) and ``clipped_text`` (input
quoted in reports, bounded) import nothing of ours and come before every stage; ``keyframe`` and ``sync``
(a keyframe, and pairing messages into keyframes) import nothing from core but ``map/`` and every stage may
take them; ``mapping`` (SemanticMapper), ``session`` (its life), ``map_store`` (crash-safe snapshots),
``warm_up`` and ``object_geometry`` (an object's one geometry) sit above every stage and may import all of
them. Nothing in core imports from outside it (tests/test_layering.py holds both rules).
"""

from monovoc_ros.core.thread_pools import passive_openmp

passive_openmp()  # before the first numba parallel kernel of the process (core.thread_pools)
