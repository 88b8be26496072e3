"""ooi_seg_ros.sfm: SfM clouds from posed image streams (incremental) or photo sets (mapping)."""

from __future__ import annotations


def run_sfm(capture, config=None):
    """The SfM cloud of a ``Capture`` (see ``sfm.pipeline.reconstruct``)."""
    from .pipeline import run_sfm as _run
    return _run(capture, config)
