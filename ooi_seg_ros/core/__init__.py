"""ROS-free core: shared types, geometry conventions, configuration helpers."""
