"""The ROS-free core: Gaussian maps, the SCD rasterizer, semantic state, palettes, evaluation."""
