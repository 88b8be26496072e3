"""Rotations, pose interpolation, projection and frame-convention conversions (ROS-free).

All conversions between the package's convention (camera-to-world, optical frame x right,
y down, z forward) and other tools' conventions (COLMAP world-to-camera, nerfstudio/OpenGL
camera-to-world with y up and z backward) live here, each with a test.
"""

from __future__ import annotations

import numpy as np

from .types import CameraIntrinsics, InputError, Pose

# OpenGL camera (x right, y up, z backward) <-> optical camera (x right, y down, z forward).
GL_TO_OPTICAL = np.diag([1.0, -1.0, -1.0])


def quat_xyzw_to_matrix(q: np.ndarray, normalize_tol: float = 1e-3) -> np.ndarray:
    """Rotation matrix [3,3] of a quaternion (x, y, z, w) as ROS stores it.

    Raises InputError for NaN/inf or a norm further than ``normalize_tol`` from 1 (a quaternion
    that is not a rotation; ROS tools reject those too); small deviations are renormalised.
    """
    q = np.asarray(q, dtype=float).reshape(4)
    if not np.all(np.isfinite(q)):
        raise InputError("pose quaternion contains NaN/inf")
    n = np.linalg.norm(q)
    if abs(n - 1.0) > normalize_tol:
        raise InputError(f"pose quaternion has norm {n:.4f}, not 1; publish unit quaternions")
    x, y, z, w = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w), w >= 0, of a rotation matrix."""
    R = np.asarray(R, dtype=float)
    tr = np.trace(R)
    if tr > 0:
        s = np.sqrt(tr + 1.0) * 2
        w, x, y, z = 0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, \
            (R[1, 0] - R[0, 1]) / s
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = np.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        w, x, y, z = (R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, \
            (R[0, 2] + R[2, 0]) / s
    elif R[1, 1] > R[2, 2]:
        s = np.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        w, x, y, z = (R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, \
            (R[1, 2] + R[2, 1]) / s
    else:
        s = np.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        w, x, y, z = (R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, \
            (R[1, 2] + R[2, 1]) / s, 0.25 * s
    q = np.array([x, y, z, w])
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


def slerp(q0: np.ndarray, q1: np.ndarray, a: float) -> np.ndarray:
    """Spherical interpolation between unit quaternions (x, y, z, w), a in [0, 1]."""
    q0 = np.asarray(q0, float)
    q1 = np.asarray(q1, float)
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + a * (q1 - q0)
        return q / np.linalg.norm(q)
    th = np.arccos(np.clip(d, -1, 1))
    return (np.sin((1 - a) * th) * q0 + np.sin(a * th) * q1) / np.sin(th)


def interpolate_pose(t0: int, p0: Pose, t1: int, p1: Pose, t: int) -> Pose:
    """Pose at stamp ``t`` (ns) between (t0, p0) and (t1, p1): linear + slerp."""
    a = 0.0 if t1 == t0 else (t - t0) / float(t1 - t0)
    q = slerp(matrix_to_quat_xyzw(p0.R), matrix_to_quat_xyzw(p1.R), a)
    return Pose(quat_xyzw_to_matrix(q), (1 - a) * p0.t + a * p1.t)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0, 0, 1.0])) -> Pose:
    """Camera-to-world pose of an optical camera at ``eye`` looking at ``target``."""
    eye = np.asarray(eye, float)
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, np.array([0, 1.0, 0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Pose(np.stack([x, y, z], axis=1), eye)


def pose_from_gl_c2w(m: np.ndarray) -> Pose:
    """Pose from a nerfstudio / OpenGL camera-to-world 4x4 (y up, z backward)."""
    m = np.asarray(m, float)
    return Pose(m[:3, :3] @ GL_TO_OPTICAL, m[:3, 3].copy())


def pose_to_gl_c2w(p: Pose) -> np.ndarray:
    """nerfstudio / OpenGL camera-to-world 4x4 of a pose."""
    m = np.eye(4)
    m[:3, :3] = p.R @ GL_TO_OPTICAL
    m[:3, 3] = p.t
    return m


def pose_from_colmap(qvec_wxyz: np.ndarray, tvec: np.ndarray) -> Pose:
    """Pose from COLMAP's world-to-camera quaternion (w, x, y, z) and translation."""
    w, x, y, z = np.asarray(qvec_wxyz, float)
    R_cw = quat_xyzw_to_matrix(np.array([x, y, z, w]), normalize_tol=1e-2)
    return Pose(R_cw.T, -R_cw.T @ np.asarray(tvec, float))


_BLOCK = 32768  # rows per block of ``to_camera``


def to_camera(points: np.ndarray, pose: Pose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera-frame coordinates (x, y, z), each [N], of world points [N, 3].

    Written out per column: NumPy's ``[N, 3] @ [3, 3]`` runs 3-4x slower than these
    multiply-adds for the crop-sized point sets the refinement projects many times over
    (``benchmarks/bench_seg_speed.py --primitives``)."""
    R_cw, t_cw = pose.world_to_cam()
    p = np.asarray(points, float)
    out = np.empty((3, len(p)))
    for s in range(0, len(p), _BLOCK):  # blocks that stay in cache (a 1M-voxel grid)
        x, y, z = p[s:s + _BLOCK, 0], p[s:s + _BLOCK, 1], p[s:s + _BLOCK, 2]
        for k in range(3):
            out[k, s:s + _BLOCK] = R_cw[k, 0] * x + R_cw[k, 1] * y + R_cw[k, 2] * z + t_cw[k]
    return out[0], out[1], out[2]


def finite_rows(a: np.ndarray) -> np.ndarray:
    """[N] bool: rows of an [N, 2] array (pixel coordinates) with both entries finite
    (``np.isfinite(a).all(1)`` reduces along the short axis several times slower)."""
    return np.isfinite(a[:, 0]) & np.isfinite(a[:, 1])


def project(points: np.ndarray, cam: CameraIntrinsics,
            pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates [N,2] and depths [N] of world points in an undistorted pinhole view."""
    xc, yc, z = to_camera(points, pose)
    uv = np.empty((len(z), 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        uv[:, 0] = cam.fx * xc / z + cam.cx
        uv[:, 1] = cam.fy * yc / z + cam.cy
    return uv, z


def pixel_rays(cam: CameraIntrinsics, pose: Pose,
               stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Ray origins [H*W,3] and unit directions [H*W,3] through pixel centres (row-major)."""
    us = np.arange(0, cam.width, stride, dtype=float)
    vs = np.arange(0, cam.height, stride, dtype=float)
    uu, vv = np.meshgrid(us, vs)
    d = np.stack([(uu - cam.cx) / cam.fx, (vv - cam.cy) / cam.fy, np.ones_like(uu)], -1)
    d = d.reshape(-1, 3) @ pose.R.T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(pose.t, d.shape).copy()
    return o, d


def cameras_convergence_point(poses: list[Pose]) -> np.ndarray:
    """Least-squares point closest to all optical axes (where an orbit's cameras look)."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for p in poses:
        d = p.forward / np.linalg.norm(p.forward)
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ p.t
    return np.linalg.lstsq(A, b, rcond=None)[0]
