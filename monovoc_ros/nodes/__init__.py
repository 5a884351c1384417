"""ROS 2 nodes of monovoc_ros (rclpy). `semantic_mapper`: the live semantic mapping node."""
