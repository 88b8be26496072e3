"""ooi_seg_ros.sim"""
