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


def test_worker_runs_below_the_callers_priority():
    import os
    base = os.getpriority(os.PRIO_PROCESS, 0)
    w = SegmentationWorker(nice=5)
    try:
        assert w.nice == 5
        assert os.getpriority(os.PRIO_PROCESS, w.pid) == min(19, base + 5)
    finally:
        w.close(timeout=5.0)
    w = SegmentationWorker()
    try:
        assert w.nice == 0 and os.getpriority(os.PRIO_PROCESS, w.pid) == base
    finally:
        w.close(timeout=5.0)


def test_context_masks_replace_refining_the_other_views(case):
    """With hull_add on, a view subset normally refines every view (the hull needs all
    masks); given the other views' masks it refines only the subset, and with the full
    run's own masks as context it makes the full run's masks."""
    cap, cloud = case
    cfg = make_config("ours")
    assert cfg.refine.hull_add
    full = segment(Capture(cap.views), cloud, cfg)
    keys = [v.key for v in cap.views[::4]]
    ctx = {k: m for k, m in full.masks.items() if k not in keys}
    # context: the full run's final masks of the other views (after matting, as a node keeps)
    sub = segment(Capture(cap.views), cloud, cfg, mask_keys=keys, context_masks=ctx)
    assert set(sub.masks) == set(keys)
    assert sub.params["refine"]["hull_add"]["context_views"] == len(ctx)
    assert sub.params["refine"]["refined"] <= len(keys)
    w = SegmentationWorker()
    try:  # the worker gets the context masks (bit-packed) and makes the same masks
        got = w.segment(cap.views, cloud, cfg, mask_keys=keys, context_masks=ctx)
    finally:
        w.close()
    for k in keys:
        np.testing.assert_array_equal(got.masks[k], sub.masks[k])
    for k in keys:
        # the hull from final (matted) masks instead of pre-hull ones: nearly the same mask
        # (0.958 IoU at worst on these 128x96 views of ~1300 object pixels)
        inter = (sub.masks[k] & full.masks[k]).sum()
        union = (sub.masks[k] | full.masks[k]).sum()
        assert inter >= 0.93 * union, (k, inter / union)
    # context missing for one view: every view is refined again (the same masks as a full run)
    partial = dict(ctx)
    partial.pop(next(iter(partial)))
    sub2 = segment(Capture(cap.views), cloud, cfg, mask_keys=keys, context_masks=partial)
    assert "context_views" not in sub2.params["refine"]["hull_add"] or \
        sub2.params["refine"]["hull_add"]["context_views"] == 0
    for k in keys:
        np.testing.assert_array_equal(sub2.masks[k], full.masks[k])
