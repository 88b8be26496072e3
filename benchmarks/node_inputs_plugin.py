"""pytest plugin: keep what the segmentation node segments, to replay it offline.

The node integration test (``test/test_nodes_pipeline.py``) scores the masks the running
nodes publish from the SfM cloud the nodes built themselves. That cloud exists only inside the
test. With this plugin the segmentation node writes the inputs of its full runs (keyframe
views, full-size cameras, the SfM cloud with its observations, the node's own segmentation
config) to a pickle, each run replacing the last; ``bench_seg_node_inputs.py`` then runs
``segment`` on them with other settings, without ROS:

    OOI_DUMP_NODE_INPUTS=/tmp/node_inputs.pkl PYTHONPATH=benchmarks \\
        .venv/bin/python -m pytest -p node_inputs_plugin -q -s \\
        test/test_nodes_pipeline.py::test_nodes_on_demo_bag

The patch only wraps ``SegmentationNode._inputs``; what the node computes is unchanged.
"""

from __future__ import annotations

import os
import pickle

from ooi_seg_ros.nodes import segmentation_node as _sn

_ORIG = _sn.SegmentationNode._inputs
PATH = os.environ.get("OOI_DUMP_NODE_INPUTS", "/tmp/node_inputs.pkl")


def _inputs(self, observations: bool = True):
    got = _ORIG(self, observations)
    if got is not None and observations:  # a full run (the cloud-only runs skip observations)
        views, full, cloud, _seq, _stamp = got
        tmp = PATH + ".part"
        with open(tmp, "wb") as f:
            pickle.dump({"views": views, "full": full, "cloud": cloud, "cfg": self.seg_cfg}, f)
        os.replace(tmp, PATH)
    return got


_sn.SegmentationNode._inputs = _inputs
