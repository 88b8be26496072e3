"""Frame-convention conversions and core types: one test per conversion."""

import numpy as np
import pytest

from ooi_seg_ros.core import geometry as g
from ooi_seg_ros.core.types import CameraIntrinsics, InputError, Pose, SfmCloud


def _rand_rot(rng):
    q = rng.normal(size=4)
    return g.quat_xyzw_to_matrix(q / np.linalg.norm(q))


def test_quaternion_roundtrip():
    rng = np.random.default_rng(0)
    for _ in range(50):
        R = _rand_rot(rng)
        R2 = g.quat_xyzw_to_matrix(g.matrix_to_quat_xyzw(R))
        np.testing.assert_allclose(R, R2, atol=1e-12)
        assert np.isclose(np.linalg.det(R), 1.0)


def test_quaternion_rejects_nan_and_non_unit():
    with pytest.raises(InputError, match="NaN"):
        g.quat_xyzw_to_matrix([np.nan, 0, 0, 1])
    with pytest.raises(InputError, match="norm"):
        g.quat_xyzw_to_matrix([0, 0, 0, 2.0])


def test_look_at_is_optical_frame():
    p = g.look_at(np.array([5.0, 0, 2]), np.zeros(3))
    cam = CameraIntrinsics(100, 80, 50, 50, 49.5, 39.5)
    uv, z = g.project(np.zeros((1, 3)), cam, p)
    np.testing.assert_allclose(uv[0], [49.5, 39.5], atol=1e-9)
    assert z[0] > 0
    # y (down in the image) points towards -z of the world for an upright camera
    assert p.R[:, 1][2] < 0
    # a point above the target projects above the image centre (smaller v)
    uv_up, _ = g.project(np.array([[0, 0, 1.0]]), cam, p)
    assert uv_up[0, 1] < 39.5


def test_gl_conversion_roundtrip_and_meaning():
    p = g.look_at(np.array([1.0, 2, 3]), np.zeros(3))
    m = g.pose_to_gl_c2w(p)
    # OpenGL cameras look down their -z axis
    np.testing.assert_allclose(-m[:3, 2], p.forward, atol=1e-12)
    p2 = g.pose_from_gl_c2w(m)
    np.testing.assert_allclose(p2.matrix(), p.matrix(), atol=1e-12)


def test_colmap_conversion():
    rng = np.random.default_rng(1)
    R_cw = _rand_rot(rng)
    t_cw = rng.normal(size=3)
    q = g.matrix_to_quat_xyzw(R_cw)
    p = g.pose_from_colmap(np.array([q[3], q[0], q[1], q[2]]), t_cw)
    R2, t2 = p.world_to_cam()
    np.testing.assert_allclose(R2, R_cw, atol=1e-12)
    np.testing.assert_allclose(t2, t_cw, atol=1e-12)


def test_interpolate_pose_midpoint():
    p0 = Pose(np.eye(3), np.zeros(3))
    Rz = g.quat_xyzw_to_matrix([0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)])  # 90 deg about z
    p1 = Pose(Rz, np.array([2.0, 0, 0]))
    pm = g.interpolate_pose(0, p0, 10, p1, 5)
    np.testing.assert_allclose(pm.t, [1, 0, 0])
    ang = np.degrees(np.arccos((np.trace(pm.R) - 1) / 2))
    assert abs(ang - 45) < 1e-6


def test_convergence_point_of_orbit():
    target = np.array([1.0, -2.0, 0.5])
    poses = [g.look_at(target + [5 * np.cos(a), 5 * np.sin(a), 2], target)
             for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)]
    np.testing.assert_allclose(g.cameras_convergence_point(poses), target, atol=1e-9)


def test_intrinsics_validate_and_scale():
    with pytest.raises(InputError, match="K must not be all zeros"):
        CameraIntrinsics(10, 10, 0, 0, 0, 0).validate()
    cam = CameraIntrinsics(800, 600, 500, 500, 399.5, 299.5)
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (400, 300)
    assert half.cx == pytest.approx(199.5) and half.fx == pytest.approx(250)


def test_cloud_subset_keeps_observations():
    xyz = np.arange(12, dtype=float).reshape(4, 3)
    ptr = np.array([0, 2, 3, 3, 6])
    ov = np.array([0, 1, 2, 0, 1, 2], np.int32)
    oxy = np.arange(12, dtype=np.float32).reshape(6, 2)
    c = SfmCloud(xyz, np.zeros((4, 3), np.uint8), np.zeros(4), ptr, ov, oxy)
    s = c.subset(np.array([False, True, True, True]))
    assert len(s) == 3
    np.testing.assert_array_equal(s.obs_ptr, [0, 1, 1, 4])
    np.testing.assert_array_equal(s.obs_view, [2, 0, 1, 2])
    np.testing.assert_array_equal(s.observations(2)[1], oxy[3:6])


@pytest.mark.parametrize("n", [0, 5, 70_001])  # 70,001 spans three of to_camera's blocks
def test_to_camera_and_project_match_the_matrix_form(n):
    rng = np.random.default_rng(1)
    pose = g.look_at(np.array([3.0, -2.0, 1.5]), np.zeros(3), np.array([0, 0, 1.0]))
    x = rng.normal(size=(n, 3))
    r_cw, t_cw = pose.world_to_cam()
    want = x @ r_cw.T + t_cw
    np.testing.assert_allclose(np.stack(g.to_camera(x, pose), 1), want, atol=1e-12)
    cam = CameraIntrinsics(320, 240, 300.0, 300.0, 160.0, 120.0)
    uv, z = g.project(x, cam, pose)
    assert uv.shape == (n, 2) and z.shape == (n,)
    with np.errstate(divide="ignore", invalid="ignore"):
        np.testing.assert_allclose(uv[:, 0], 300.0 * want[:, 0] / want[:, 2] + 160.0)
    bad = np.array([[np.nan, 1.0], [1.0, 2.0], [np.inf, np.nan], [3.0, -np.inf]])
    assert g.finite_rows(bad).tolist() == [False, True, False, False]
