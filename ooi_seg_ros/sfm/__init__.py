"""ooi_seg_ros.sfm"""
