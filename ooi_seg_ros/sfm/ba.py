"""Bundle adjustment of an ``SfmCloud`` with pycolmap (points only, or points and poses)."""

from __future__ import annotations

import copy
import tempfile
from pathlib import Path

import numpy as np

from ..core.types import Pose, SfmCloud
from .export import write_colmap_model


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising ||s R src + t - dst||^2 over point pairs [N,3]."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var = (a ** 2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var) if var > 0 else 1.0
    return s, R, mu_d - s * R @ mu_s


def bundle_adjust(cloud: SfmCloud, refine_poses: bool = False,
                  max_iterations: int = 50) -> tuple[SfmCloud, dict]:
    """Refine the points (and with ``refine_poses`` the keyframe poses) of ``cloud``.

    Intrinsics stay fixed. With pose refinement the result is mapped back onto the input
    camera centres by a similarity (BA alone leaves the 7-DoF gauge free), so the cloud stays in
    the map frame of the known poses. Returns a new cloud (views copied when poses change) and the
    mean reprojection error before/after in pixels.
    """
    import pycolmap

    if len(cloud) == 0:
        return cloud, {"skipped": "empty cloud"}
    with tempfile.TemporaryDirectory(prefix="sfm_ba_") as tmp:
        write_colmap_model(cloud, Path(tmp))
        rec = pycolmap.Reconstruction(tmp)
    before = float(rec.compute_mean_reprojection_error())
    opt = pycolmap.BundleAdjustmentOptions()
    opt.refine_focal_length = False
    opt.refine_principal_point = False
    opt.refine_extra_params = False
    opt.refine_points3D = True
    opt.refine_rig_from_world = bool(refine_poses)
    opt.print_summary = False
    opt.ceres.solver_options.max_num_iterations = max_iterations
    pycolmap.bundle_adjustment(rec, opt)
    after = float(rec.compute_mean_reprojection_error())
    out = copy.copy(cloud)
    out.xyz = np.stack([np.asarray(rec.points3D[i + 1].xyz) for i in range(len(cloud))])
    out.error = np.array([rec.points3D[i + 1].error for i in range(len(cloud))])
    if refine_poses:
        poses = []
        for k in range(len(cloud.views)):
            cfw = rec.images[k + 1].cam_from_world()
            R_cw = np.asarray(cfw.rotation.matrix())
            t_cw = np.asarray(cfw.translation)
            poses.append(Pose(R_cw.T, -R_cw.T @ t_cw))
        if len(poses) >= 3:
            s, R, t = umeyama(np.stack([p.t for p in poses]),
                              np.stack([v.pose.t for v in cloud.views]))
        else:
            s, R, t = 1.0, np.eye(3), np.zeros(3)
        out.xyz = s * out.xyz @ R.T + t
        views = []
        for v, p in zip(cloud.views, poses):
            nv = copy.copy(v)
            nv.pose = Pose(R @ p.R, s * R @ p.t + t)
            views.append(nv)
        out.views = views
    return out, {"mean_reprojection_px_before": before, "mean_reprojection_px_after": after,
                 "refine_poses": bool(refine_poses)}
