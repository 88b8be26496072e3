"""Fixtures shared by several test modules."""

import pytest

from ooi_seg_ros.seg.proxy import depth_proxy_cloud
from ooi_seg_ros.sim import simulate_capture


@pytest.fixture(scope="module")
def aircraft():
    """A small simulator capture (12 views, 128x96) and a depth-proxy cloud of it."""
    sim = simulate_capture("aircraft", n_views=12, width=128, height=96, seed=0)
    return sim, depth_proxy_cloud(sim, 300, seed=0)
