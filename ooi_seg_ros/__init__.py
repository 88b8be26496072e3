"""ooi_seg_ros: object-of-interest segmentation and object-only 3D Gaussian splatting for ROS 2.

The package is split into a ROS-free core (``ooi_seg_ros.core``, ``sim``, ``sfm``, ``seg``,
``train``, ``bag``) and thin ROS 2 nodes (``ooi_seg_ros.nodes``). Only ``nodes`` and the
message conversion layer import ROS message packages / rclpy.
"""

__version__ = "0.1.0"
