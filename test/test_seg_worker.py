"""The segmentation worker process gives the calling process's results (nodes use it)."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from ooi_seg_ros.core.types import Capture, InputError, SfmCloud
from ooi_seg_ros.core.worker import SubprocessWorker, WorkerDied
from ooi_seg_ros.seg.pipeline import make_config, segment
from ooi_seg_ros.seg.proxy import depth_proxy_cloud
from ooi_seg_ros.seg.worker import SegmentationWorker, point_stages
from ooi_seg_ros.sim import simulate_capture


@pytest.fixture(scope="module")
def case():
    sim = simulate_capture("aircraft", n_views=12, width=128, height=96, seed=0)
    for v in sim.capture.views:
        v.gt_mask = None  # as in a node: no ground truth
    return sim.capture, depth_proxy_cloud(sim, 300, seed=0)


def test_worker_matches_in_process(case):
    cap, cloud = case
    cfg = make_config("ours")
    ref = segment(Capture(cap.views), cloud, cfg)
    keys = [v.key for v in cap.views[::3]]
    ref_sub = segment(Capture(cap.views), cloud, cfg, mask_keys=keys)
    w = SegmentationWorker()
    try:
        xyz, rgb = w.point_stages(cap.views, cloud, cfg)
        np.testing.assert_array_equal(xyz, ref.ooi_cloud.xyz)
        np.testing.assert_array_equal(rgb, ref.ooi_cloud.rgb)
        got = w.segment(cap.views, cloud, cfg)
        assert set(got.masks) == set(ref.masks)
        for k in ref.masks:
            np.testing.assert_array_equal(got.masks[k], ref.masks[k])
        # Poisson's vertex order and last float bits depend on its thread count (the worker
        # runs one OpenMP thread): the same vertices, in another order
        assert got.mesh.vertices.shape == ref.mesh.vertices.shape
        diag = float(np.ptp(ref.mesh.vertices, axis=0).max())
        d, _ = cKDTree(ref.mesh.vertices).query(got.mesh.vertices)
        assert d.max() < 1e-4 * diag
        # a second run sends no images (the worker kept them) and gives the subset's masks
        got_sub = w.segment(cap.views[:-1] + cap.views[-1:], cloud, cfg, mask_keys=keys)
        assert set(got_sub.masks) == set(keys)
        for k in keys:
            np.testing.assert_array_equal(got_sub.masks[k], ref_sub.masks[k])
        # an input error in the worker is raised in the caller; the worker lives on
        empty = SfmCloud.empty(cap.views)
        with pytest.raises(InputError):
            w.segment(cap.views, empty, cfg)
        assert w.alive
        # the in-process point stages agree too
        np.testing.assert_array_equal(point_stages(Capture(cap.views), cloud, cfg).xyz, xyz)
        assert all(v.image is not None for v in cap.views)  # the caller's views keep pixels
    finally:
        w.close()


def test_dead_worker_fails_pending_futures():
    w = SubprocessWorker("ooi_seg_ros.seg.worker:_segment_job", None, name="test")
    w.proc.kill()
    w.proc.wait()
    with pytest.raises(WorkerDied):
        w.submit(("points",) + (None,) * 6).result(timeout=30)
    w.close(timeout=1.0)
