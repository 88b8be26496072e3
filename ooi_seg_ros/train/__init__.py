"""ooi_seg_ros.train"""
