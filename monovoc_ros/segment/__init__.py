"""Instance segmentation of keyframe images: RGB -> per-frame instance ids, class names and scores.

What a robot with only a camera needs before the mapper: each keyframe's image segmented into instances
numbered per frame (0 = void), each named by the segmenter's class with its score. Backends are small
explicit types behind :class:`monovoc_ros.segment.backend.Segmenter` (the first: YOLO-seg ONNX run by
onnxruntime); decoding is NumPy/OpenCV. ROS-free: it may import numpy, scipy, opencv, onnxruntime,
``monovoc_ros.core`` (the mask, segment and dataset formats) and ``monovoc_ros.embed``'s model store and
onnxruntime sessions (one model directory, one way to verify it), never the nodes.
"""
