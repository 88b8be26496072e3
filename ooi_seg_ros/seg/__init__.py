"""ooi_seg_ros.seg"""
