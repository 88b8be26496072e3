"""ooi_seg_ros.nodes"""
