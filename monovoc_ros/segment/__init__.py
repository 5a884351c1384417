"""Instance segmentation of keyframe images: RGB -> per-frame instance ids, class names and scores.

What a robot with only a camera needs before the mapper: each keyframe's image segmented into instances
numbered per frame (0 = void), each named by the segmenter's class with its score. Backends are small
explicit types behind :class:`monovoc_ros.segment.backend.Segmenter` (the first: YOLO-seg ONNX run by
onnxruntime); decoding is NumPy/OpenCV. ROS-free: it may import numpy, opencv, onnxruntime and
``monovoc_ros.core`` (for the mask and segment formats), never the nodes.
"""
