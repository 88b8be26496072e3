"""PoseBuffer: interpolation at image stamps, tolerance, rejection counting, bounded memory."""

import numpy as np

from ooi_seg_ros.core.geometry import look_at, matrix_to_quat_xyzw, quat_xyzw_to_matrix
from ooi_seg_ros.core.sync import PoseBuffer, apply_mount
from ooi_seg_ros.core.types import Pose

MS = 1_000_000


def _orbit(t_ns):
    a = t_ns / 1e9
    return look_at(np.array([2 * np.cos(a), 2 * np.sin(a), 1.0]), np.zeros(3))


def test_interpolates_between_bracketing_poses():
    buf = PoseBuffer(max_age_ns=10_000 * MS, tolerance_ns=60 * MS)
    for t in range(0, 1000 * MS, 50 * MS):
        assert buf.add(t, _orbit(t))
    p = buf.lookup(125 * MS)
    truth = _orbit(125 * MS)
    assert np.allclose(p.R, truth.R, atol=1e-3)
    assert np.linalg.norm(p.t - truth.t) < 2e-3  # chord vs arc over 50 ms
    exact = buf.lookup(100 * MS)
    assert np.allclose(exact.t, _orbit(100 * MS).t)
    assert buf.lookup(-1) is None and buf.lookup(2000 * MS) is None
    assert not buf.is_too_old(2000 * MS)  # a later pose may still come
    assert buf.is_too_old(-1)


def test_tolerance_and_gaps():
    buf = PoseBuffer(tolerance_ns=30 * MS)
    buf.add(0, _orbit(0))
    buf.add(100 * MS, _orbit(100 * MS))
    assert buf.lookup(50 * MS) is None  # both neighbours 50 ms away
    assert buf.is_too_old(50 * MS)
    buf2 = PoseBuffer(tolerance_ns=60 * MS)
    buf2.add(0, _orbit(0))
    buf2.add(100 * MS, _orbit(100 * MS))
    assert buf2.lookup(50 * MS) is not None


def test_rejects_and_counts_bad_poses():
    buf = PoseBuffer()
    assert buf.add(10, _orbit(10))
    assert not buf.add(10, _orbit(10))
    assert not buf.add(5, _orbit(5))
    nan = Pose(np.eye(3), np.array([np.nan, 0, 0]))
    assert not buf.add(20, nan)
    skew = Pose(np.eye(3) * 2, np.zeros(3))
    assert not buf.add(30, skew)
    assert dict(buf.rejected) == {"stamp_not_increasing": 2, "invalid_pose": 2}
    assert len(buf) == 1


def test_bounded_memory():
    buf = PoseBuffer(max_age_ns=100 * MS, tolerance_ns=10 * MS, max_len=50)
    for i in range(1000):
        buf.add(i * MS, _orbit(i * MS))
    assert len(buf) == 50
    buf2 = PoseBuffer(max_age_ns=20 * MS, max_len=10_000)
    for i in range(1000):
        buf2.add(i * MS, _orbit(i * MS))
    assert len(buf2) == 21 and buf2.latest_ns == 999 * MS


def test_mount_transform():
    mount = Pose(quat_xyzw_to_matrix(np.array([0.5, -0.5, 0.5, -0.5])), np.array([0.1, 0, -0.05]))
    body = Pose(quat_xyzw_to_matrix(np.array([0, 0, np.sin(0.3), np.cos(0.3)])),
                np.array([1.0, 2.0, 3.0]))
    buf = PoseBuffer(mount=mount)
    buf.add(0, body)
    cam = buf.lookup(0)
    assert np.allclose(cam.matrix(), body.matrix() @ mount.matrix())
    assert apply_mount(body, None) is body
    assert np.allclose(np.linalg.norm(matrix_to_quat_xyzw(cam.R)), 1.0)
