"""Simulator ground truth: scenes, masks, contact with the support, poses, distances."""

import numpy as np
import open3d as o3d
import pytest

from ooi_seg_ros.core.geometry import project
from ooi_seg_ros.core.types import InputError
from ooi_seg_ros.sim import (SCENES, Renderer, intrinsics_from_fov, make_scene, orbit_poses,
                             simulate_capture)


def test_scene_list_and_scales():
    assert set(SCENES) >= {"aircraft", "tabletop", "bicycle"}
    diags = {name: make_scene(name, 0).ooi_diagonal for name in SCENES}
    # scale-dependent parameters must be exercised: aircraft tens of metres, tabletop tens of cm
    assert diags["aircraft"] > 15.0
    assert diags["tabletop"] < 1.0
    assert diags["aircraft"] / diags["tabletop"] > 10.0
    for name in SCENES:
        sc = make_scene(name, 0)
        assert sc.scene_size > 3 * sc.ooi_diagonal, name  # there is background around it
        assert sc.background_mesh().triangles.shape[0] > sc.ooi_mesh().triangles.shape[0] / 10


def test_unknown_scene_is_input_error():
    with pytest.raises(InputError, match="unknown scene"):
        make_scene("submarine", 0)
    with pytest.raises(InputError):
        simulate_capture("tabletop", n_views=0, width=32, height=24)
    with pytest.raises(InputError, match="ring"):
        simulate_capture("tabletop", n_views=2, width=32, height=24, rings=[(30.0,)])


@pytest.mark.parametrize("name", SCENES)
def test_ooi_touches_support(name):
    sc = make_scene(name, 0)
    lo, hi = sc.ooi_bbox
    scale = sc.ooi_diagonal
    assert abs(lo[2] - sc.support_z) < 1e-6 * scale  # lowest OOI point is on the support
    # the support really is there: straight down from the lowest OOI points there is a
    # background surface at the contact height, and no gap
    V = sc.ooi_mesh().vertices
    low = V[V[:, 2] < sc.support_z + 1e-6 * scale]
    assert len(low) >= 1
    bg = sc.background_mesh()
    rs = o3d.t.geometry.RaycastingScene()
    rs.add_triangles(o3d.core.Tensor(bg.vertices.astype(np.float32)),
                     o3d.core.Tensor(bg.triangles.astype(np.uint32)))
    eps = 1e-3 * scale
    rays = np.concatenate([low + [0, 0, eps], np.tile([0, 0, -1.0], (len(low), 1))], 1)
    t = rs.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
    assert np.all(np.abs(t - eps) < 1e-3 * scale)


def test_gt_points_on_surface_and_distance_helpers():
    sc = make_scene("bicycle", 0)
    pts = sc.sample_ooi_points(2000, seed=1)
    assert pts.shape == (2000, 3)
    assert np.array_equal(pts, sc.sample_ooi_points(2000, seed=1))
    d = sc.distance_to_ooi(pts)
    assert np.max(d) < 1e-4 * sc.ooi_diagonal
    # points straight above the top of the OOI are as far from it as they are high
    lo, hi = sc.ooi_bbox
    top = pts[np.argmax(pts[:, 2])]
    up = np.array([top + [0, 0, h] for h in (0.05, 0.1, 0.2)])
    np.testing.assert_allclose(sc.distance_to_ooi(up), [0.05, 0.1, 0.2], atol=2e-3)
    # the support is a surface too: a point above the lawn far from the bike
    far = np.array([[20.0, -5.0, 0.3]])
    assert sc.distance_to_surface(far)[0] <= 0.3 + 1e-4
    assert sc.distance_to_ooi(far)[0] > 15.0


@pytest.mark.parametrize("name", SCENES)
def test_masks_match_ground_truth(name):
    sim = simulate_capture(name, n_views=3, width=128, height=96, seed=0)
    sc = sim.scene
    pts = sim.capture.gt_ooi_points
    tol = 0.01 * sc.ooi_diagonal
    for v, depth in zip(sim.capture.views, sim.depths):
        m = v.gt_mask
        assert m.dtype == bool and m.shape == (96, 128)
        assert 0.005 < m.mean() < 0.7, m.mean()  # non-empty, not the whole image
        # visible GT OOI points project into the mask
        uv, z = project(pts, v.camera, v.pose)
        px = np.round(uv).astype(int)
        inside = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < 128) & (px[:, 1] >= 0) & \
            (px[:, 1] < 96)
        px, z = px[inside], z[inside]
        visible = np.abs(depth[px[:, 1], px[:, 0]] - z) < tol
        assert visible.sum() > 50
        # a point projects into the mask or next to it (thin parts: a spoke covering less
        # than half of a pixel is not in the majority mask)
        md = m.copy()
        md[1:] |= m[:-1]
        md[:-1] |= m[1:]
        md[:, 1:] |= md[:, :-1].copy()
        md[:, :-1] |= md[:, 1:].copy()
        hit = md[px[visible, 1], px[visible, 0]]
        assert hit.mean() > 0.9, hit.mean()
        # mask pixels back-project onto the OOI surface, other pixels do not
        vv, uu = np.nonzero(np.isfinite(depth))
        dd = depth[vv, uu]
        cam = v.camera
        xc = np.stack([(uu - cam.cx) / cam.fx * dd, (vv - cam.cy) / cam.fy * dd, dd], 1)
        X = xc @ v.pose.R.T + v.pose.t
        dist = sc.distance_to_ooi(X)
        on = m[vv, uu]
        assert np.mean(dist[on] < tol) > 0.9
        assert np.mean(dist[~on] > tol * 0.1) > 0.97


@pytest.mark.parametrize("name", SCENES)
def test_pose_convention_looks_at_ooi(name):
    sc = make_scene(name, 0)
    cam = intrinsics_from_fov(320, 240, 60.0)
    poses = orbit_poses(sc, 12, seed=0)
    lo, hi = sc.camera_bounds
    for pose in poses:
        R = pose.R
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) > 0.999
        assert R[2, 1] < 0  # optical y points down in the world (camera upright)
        assert np.all(pose.t >= lo - 1e-9) and np.all(pose.t <= hi + 1e-9)
        uv, z = project(sc.ooi_center[None], cam, pose)
        assert z[0] > 0
        # aim jitter is small: the OOI centre is near the image centre
        assert abs(uv[0, 0] - cam.cx) < 0.2 * cam.width
        assert abs(uv[0, 1] - cam.cy) < 0.2 * cam.height
    # several rings: several heights
    assert len(np.unique(np.round([p.t[2] for p in poses], 6))) >= 3


def test_supersampling_changes_edges_only():
    sc = make_scene("tabletop", 0)
    r = Renderer(sc)
    cam = intrinsics_from_fov(96, 72, 60.0)
    pose = orbit_poses(sc, 4, seed=0)[1]
    a = r.render(cam, pose, supersample=1, sensor_noise=0)
    b = r.render(cam, pose, supersample=2, sensor_noise=0)
    assert np.mean(a.mask != b.mask) < 0.05
    diff = np.abs(a.rgb.astype(int) - b.rgb.astype(int)).max(2)
    assert np.median(diff) <= 3  # interiors are textured the same way


def test_lens_distortion_is_rendered():
    """With plumb_bob distortion, GT points land in the mask at their *distorted* pixels."""
    from ooi_seg_ros.sim.render import distort_normalized, undistort_normalized

    sim = simulate_capture("toycar", n_views=2, width=128, height=96, seed=0,
                           distortion=[-0.25, 0.08, 0.001, -0.001, 0.0])
    cam = sim.capture.views[0].camera
    assert cam.distortion_model == "plumb_bob" and cam.dist[0] == -0.25
    x = np.linspace(-0.6, 0.6, 7)
    xu, yu = undistort_normalized(*distort_normalized(x, x[::-1], cam), cam)
    np.testing.assert_allclose(xu, x, atol=1e-9)
    np.testing.assert_allclose(yu, x[::-1], atol=1e-9)
    pts = sim.capture.gt_ooi_points
    for v, depth in zip(sim.capture.views, sim.depths):
        R_cw, t_cw = v.pose.world_to_cam()
        pc = pts @ R_cw.T + t_cw
        z = pc[:, 2]
        xd, yd = distort_normalized(pc[:, 0] / z, pc[:, 1] / z, cam)
        px = np.round(np.stack([cam.fx * xd + cam.cx, cam.fy * yd + cam.cy], 1)).astype(int)
        ok = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < 128) & (px[:, 1] >= 0) & (px[:, 1] < 96)
        px, z = px[ok], z[ok]
        vis = np.abs(depth[px[:, 1], px[:, 0]] - z) < 0.01 * sim.scene.ooi_diagonal
        assert vis.sum() > 50
        assert v.gt_mask[px[vis, 1], px[vis, 0]].mean() > 0.85
