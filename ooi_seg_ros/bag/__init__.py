"""ooi_seg_ros.bag"""
