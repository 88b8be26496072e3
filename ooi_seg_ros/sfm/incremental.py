"""Incremental SfM with known poses (the drone case).

Each keyframe: SIFT (pycolmap) on the grey image (optionally with its first octave upsampled
only for small images, bounding the extraction cost as frames grow), keypoints undistorted
to normalised camera coordinates, pairs chosen from the poses (sequential neighbours plus the
keyframes whose view frustums overlap most), mutual-nearest-neighbour matching with Lowe's
ratio test, and geometric verification with the epipolar geometry the known poses imply
(Sampson distance in pixels). With ``epipolar_band_matching`` the pair's matches are then
completed by the same test among the candidates near each feature's epipolar line only: a
feature on a thin part (a wing tip, a spoke) whose descriptor has near-twins elsewhere in the
image fails the global ratio test but is unambiguous along its line.
Verified matches are merged into tracks by an incremental union-find. ``cloud()`` triangulates
only tracks that changed since the last call (multi-view DLT with the poses fixed), drops
observations with a large reprojection error, and keeps points with enough triangulation angle
and track length. Every point keeps its colour, reprojection error and observations.

The emitted cloud holds every point seen by 3+ keyframes but only the 2-view points that are
about as well conditioned as those (position uncertainty from the ray geometry, reprojection
error): a wrong match that lies on the epipolar line passes the epipolar check and cannot be
caught by reprojection error in two views, and these points carry most of the inaccuracy.
Optional guided matching projects known points into each new keyframe to grow their tracks.
"""

from __future__ import annotations

import logging
import threading
import time
import warnings
from collections import Counter
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..core.geometry import cameras_convergence_point
from ..core.types import CameraIntrinsics, InputError, SfmCloud, View

LOG = logging.getLogger(__name__)


@dataclass
class IncrementalConfig:
    """Options of the known-pose incremental SfM."""

    max_features: int = 4096  # SIFT features per keyframe
    peak_threshold: float = 0.0066  # SIFT contrast threshold (COLMAP default / octave count)
    sift_upsample_max_pixels: int = 0  # > 0: SIFT doubles the image for its first octave
    # (finer features; 4x the scale-space work, most of the extraction time) only while the
    # doubled image has at most this many pixels, so larger frames cost less; 0 = always
    # (COLMAP's default). Off: at 640x480 it was 2.5x cheaper on one scene but lost accuracy
    # on another (see BENCHMARKS)
    ratio: float = 0.8  # Lowe ratio test: best/second-best descriptor distance below this
    sequential_pairs: int = 3  # match with this many previous keyframes in capture order
    overlap_pairs: int = 5  # ... plus this many other keyframes with the largest view overlap
    min_overlap: float = 0.25  # frustum-overlap fraction needed for an overlap pair
    epipolar_px: float = 2.0  # Sampson distance (pixels) for a match to be verified
    min_inliers: int = 12  # a pair with fewer verified matches contributes none
    max_reproj_px: float = 2.0  # observations reprojecting worse than this are dropped
    min_tri_angle_deg: float = 1.5  # points seen under a smaller max ray angle are dropped
    min_track_length: int = 2  # points need this many observing keyframes
    refine_iters: int = 3  # Gauss-Newton steps on each point's reprojection error (poses fixed)
    epipolar_band_matching: bool = False  # ratio test and mutual check among the candidates
    # within ``epipolar_px`` of the epipolar line only (the known poses restrict the search):
    # descriptors repeated elsewhere in the image no longer fail the ratio test
    guided_matching: bool = False  # extend known points into each new keyframe by projection
    # (longer tracks, but merges tracks on thin repeated structure: fewer points; see BENCHMARKS)
    conditioned_two_view: bool = True  # cloud(): emit only the well-conditioned 2-view points:
    two_view_uncertainty_quantile: float = 0.75  # position uncertainty at most this quantile of
    # the multi-view (3+ keyframe) points' uncertainties ...
    two_view_residual_quantile: float = 0.5  # ... and reprojection error (per degree of
    # freedom) at most this quantile of the multi-view points' (a mismatch fits its rays worse)
    guided_desc_quantile: float = 0.9  # guided and band matches: descriptor distance up to
    # this quantile of the keyframe's (band: the pair's) own verified global matches
    seed: int = 0  # seed for anything random (none at present; kept for determinism)


# ----------------------------------------------------------------------------------------------
# camera models

def undistort_normalized(xy: np.ndarray, cam: CameraIntrinsics, iters: int = 20) -> np.ndarray:
    """Normalised, undistorted camera coordinates [N,2] of pixel coordinates ``xy`` [N,2]."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    xd = (xy[:, 0] - cam.cx) / cam.fx
    yd = (xy[:, 1] - cam.cy) / cam.fy
    if not cam.has_distortion:
        return np.stack([xd, yd], 1)
    d = np.zeros(8)
    dist = np.asarray(cam.dist, float)
    d[:min(8, dist.size)] = dist[:8]
    if cam.distortion_model == "equidistant":
        k1, k2, k3, k4 = d[:4]
        theta_d = np.hypot(xd, yd)
        th = theta_d.copy()
        for _ in range(iters):
            th2 = th * th
            f = th * (1 + k1 * th2 + k2 * th2**2 + k3 * th2**3 + k4 * th2**4) - theta_d
            fp = 1 + 3 * k1 * th2 + 5 * k2 * th2**2 + 7 * k3 * th2**3 + 9 * k4 * th2**4
            th = th - f / np.where(np.abs(fp) < 1e-9, 1e-9, fp)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(theta_d > 1e-12, np.tan(th) / theta_d, 1.0)
        return np.stack([xd * s, yd * s], 1)
    k1, k2, p1, p2, k3 = d[:5]
    k4, k5, k6 = (d[5:8] if cam.distortion_model == "rational_polynomial" else (0.0, 0.0, 0.0))
    x, y = xd.copy(), yd.copy()
    for _ in range(iters):  # fixed-point inversion of the Brown-Conrady model
        r2 = x * x + y * y
        radial = (1 + k1 * r2 + k2 * r2**2 + k3 * r2**3) / (1 + k4 * r2 + k5 * r2**2 + k6 * r2**3)
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = (xd - dx) / radial
        y = (yd - dy) / radial
    return np.stack([x, y], 1)


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def _sampson_px(xa: np.ndarray, xb: np.ndarray, E: np.ndarray, f: float) -> np.ndarray:
    """Sampson distance in pixels of matched normalised points ``xa`` <-> ``xb`` under ``E``."""
    x1 = np.c_[xa, np.ones(len(xa))]
    x2 = np.c_[xb, np.ones(len(xb))]
    Ex1 = x1 @ E.T
    Etx2 = x2 @ E
    num = np.sum(x2 * Ex1, 1) ** 2
    den = Ex1[:, 0]**2 + Ex1[:, 1]**2 + Etx2[:, 0]**2 + Etx2[:, 1]**2
    return np.sqrt(num / np.maximum(den, 1e-18)) * f


def _gauss_newton_step(X: np.ndarray, P: np.ndarray, x: np.ndarray) -> np.ndarray:
    """One batched Gauss-Newton step of points X [T,3] on normalised reprojection error."""
    R, t = P[..., :3], P[..., 3]
    pc = np.einsum("tlij,tj->tli", R, X) + t
    z = pc[..., 2:3]
    uv = pc[..., :2] / z
    r = (uv - x).reshape(len(X), -1)  # [T, 2L]
    J = (R[..., :2, :] - uv[..., :, None] * R[..., 2:3, :]) / z[..., None]  # [T,L,2,3]
    J = J.reshape(len(X), -1, 3)
    JtJ = np.einsum("tki,tkj->tij", J, J) + 1e-12 * np.eye(3)
    Jtr = np.einsum("tki,tk->ti", J, r)
    try:
        dx = np.linalg.solve(JtJ, Jtr[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return X
    Xn = X - dx
    return np.where(np.isfinite(Xn), Xn, X)


# ----------------------------------------------------------------------------------------------
# union-find over global feature ids

class _Tracks:
    """Incremental union-find with member lists and a set of changed roots."""

    def __init__(self) -> None:
        self.parent: list[int] = []
        self.members: dict[int, list[int]] = {}
        self.dirty: set[int] = set()

    def add(self, n: int) -> None:
        self.parent.extend(range(len(self.parent), len(self.parent) + n))

    def find(self, a: int) -> int:
        p = self.parent
        root = a
        while p[root] != root:
            root = p[root]
        while p[a] != root:
            p[a], a = root, p[a]
        return root

    def union(self, a: int, b: int) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra == rb:
            return
        ma = self.members.pop(ra, [ra])
        mb = self.members.pop(rb, [rb])
        if len(ma) < len(mb):
            ra, rb, ma, mb = rb, ra, mb, ma
        self.parent[rb] = ra
        ma.extend(mb)
        self.members[ra] = ma
        self.dirty.discard(rb)
        self.dirty.add(ra)


@dataclass
class _Keyframe:
    view: View
    xy: np.ndarray  # [n,2] pixel coords (ROS convention, as detected, distorted)
    xn: np.ndarray  # [n,2] normalised undistorted coords
    desc: np.ndarray  # [n,128] uint8, unit-length SIFT x 512 (COLMAP's storage; 4x smaller)
    rgb: np.ndarray  # [n,3] uint8 colour at each keypoint
    offset: int  # global id of feature 0
    R_cw: np.ndarray
    t_cw: np.ndarray


def _check_view(view: View) -> None:
    if view.camera is None:
        raise InputError(f"view {view.key} has no camera intrinsics (no CameraInfo received); "
                         "publish/record camera_info for the image topic")
    view.camera.validate()
    if view.pose is None:
        raise InputError(f"view {view.key} has no pose; known-pose SfM needs one per keyframe "
                         "(use the unknown-pose mapping route for photo folders)")
    R, t = np.asarray(view.pose.R, float), np.asarray(view.pose.t, float)
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise InputError(f"view {view.key} has a NaN/inf pose")
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-3 or abs(np.linalg.det(R) - 1) > 1e-3:
        raise InputError(f"view {view.key} pose rotation is not orthonormal (non-unit "
                         "quaternion?); normalise orientations before SfM")


@dataclass
class KeyframeFeatures:
    """The SIFT features of one keyframe, as ``add_keyframe`` uses them.

    Computed by ``IncrementalSfM.extract`` in the calling thread or by a worker process
    (``sfm.prefetch``); both run ``extract_features``, so the results are identical.
    """

    xy: np.ndarray  # [n,2] float64 pixel coords (ROS convention: pixel centres at integers)
    desc: np.ndarray  # [n,128] uint8 unit-length SIFT x 512
    rgb: np.ndarray  # [n,3] uint8 colour at each keypoint
    first_octave: int  # SIFT's first octave for this keyframe (-1 upsampled, 0 native)
    extract_s: float = 0.0  # wall seconds of the extraction
    extract_cpu_s: float = 0.0  # CPU seconds of the extraction (of the thread that ran it)


def sift_first_octave(config: IncrementalConfig, width: int, height: int) -> int:
    """SIFT's first octave for a ``width`` x ``height`` keyframe: -1 (upsampled) or 0.

    The upsampled octave holds 4x the image's pixels and costs most of the extraction; it is
    used only while it stays within ``config.sift_upsample_max_pixels`` (0: always).
    """
    budget = config.sift_upsample_max_pixels
    return -1 if budget <= 0 or 4 * width * height <= budget else 0


def make_sift(config: IncrementalConfig, first_octave: int):
    """A pycolmap CPU SIFT extractor with ``config``'s options (one thread)."""
    import pycolmap
    opt = pycolmap.FeatureExtractionOptions()
    opt.use_gpu = False
    opt.num_threads = 1
    opt.max_image_size = 100000
    opt.sift.max_num_features = config.max_features
    opt.sift.first_octave = first_octave
    opt.sift.peak_threshold = config.peak_threshold
    with warnings.catch_warnings():  # pycolmap.Sift takes numpy images directly
        warnings.simplefilter("ignore", DeprecationWarning)
        return pycolmap.Sift(opt, pycolmap.Device.cpu)


def extract_features(extractor, img: np.ndarray, cam: CameraIntrinsics, key: str = "",
                     first_octave: int = -1) -> KeyframeFeatures:
    """SIFT keypoints, quantised descriptors and colours of the RGB image ``img`` [H,W,3].

    ``extractor`` is ``make_sift(config, first_octave)``; ``first_octave`` is recorded only.

    Pure (no SfM state): what a worker process runs for the pipelined path. Several
    orientations at one location keep the first; pixel coordinates move from COLMAP's
    convention (centres at +0.5) to ROS's.
    """
    t0, c0 = time.perf_counter(), time.thread_time()
    if img is None or img.ndim != 3 or img.shape[2] != 3:
        raise InputError(f"view {key}: image must be RGB [H,W,3]")
    if img.shape[0] != cam.height or img.shape[1] != cam.width:
        raise InputError(f"view {key}: image {img.shape[1]}x{img.shape[0]} does not "
                         f"match camera_info {cam.width}x{cam.height}")
    grey = np.ascontiguousarray(
        (0.299 * img[..., 0] + 0.587 * img[..., 1] + 0.114 * img[..., 2]).astype(np.uint8))
    kp, desc = extractor.extract(grey)
    kp = np.asarray(kp, float).reshape(-1, 4)
    desc = np.asarray(desc, np.float32).reshape(len(kp), 128)
    if len(kp):  # several orientations at one location: keep the first
        _, first = np.unique(np.round(kp[:, :2], 2), axis=0, return_index=True)
        first = np.sort(first)
        kp, desc = kp[first], desc[first]
    xy = kp[:, :2] - 0.5  # COLMAP pixel centres at +0.5 -> ROS
    n = np.linalg.norm(desc, axis=1, keepdims=True)
    desc = np.clip(np.round(desc / np.maximum(n, 1e-12) * 512.0), 0, 255).astype(np.uint8)
    ij = np.clip(np.round(xy).astype(int), 0, [cam.width - 1, cam.height - 1])
    rgb = img[ij[:, 1], ij[:, 0]]
    return KeyframeFeatures(xy, desc, rgb, first_octave, time.perf_counter() - t0,
                            time.thread_time() - c0)


class IncrementalSfM:
    """Known-pose SfM that grows keyframe by keyframe; ``cloud()`` may be called any time."""

    def __init__(self, config: Optional[IncrementalConfig] = None,
                 scene_scale: Optional[float] = None):
        self.config = config or IncrementalConfig()
        self.keyframes: list[_Keyframe] = []
        self.tracks = _Tracks()
        self.scene_scale = scene_scale
        self.times = Counter()
        self.counts = Counter()
        self._sift: dict[int, object] = {}  # SIFT extractor per first octave
        self._tri: dict[int, Optional[tuple]] = {}  # root -> triangulated point or None
        self._n_features = 0
        # one caller at a time: a live node adds keyframes in its worker thread while a
        # service or timer asks for the cloud; ``_refresh`` takes and clears the changed
        # tracks, so two at once lost tracks for good (measured: 37 points instead of 51)
        self._lock = threading.RLock()

    # -- features ----------------------------------------------------------------------------
    def first_octave(self, width: int, height: int) -> int:
        """SIFT's first octave for a ``width`` x ``height`` keyframe (``sift_first_octave``)."""
        return sift_first_octave(self.config, width, height)

    def _extractor(self, first_octave: int = -1):
        if first_octave not in self._sift:
            self._sift[first_octave] = make_sift(self.config, first_octave)
        return self._sift[first_octave]

    def extract(self, view: View) -> KeyframeFeatures:
        """Checks ``view`` and extracts its SIFT features in this thread (no SfM state changes).

        ``add_keyframe(view, features)`` accepts the result; a worker process can compute the
        same with ``extract_features`` (see ``sfm.prefetch``) while this object matches.
        """
        _check_view(view)
        cam = view.camera
        octave = self.first_octave(cam.width, cam.height)
        return extract_features(self._extractor(octave), view.get_image(), cam, view.key,
                                octave)

    # -- pairs --------------------------------------------------------------------------------
    def _depth_guess(self, kf: _Keyframe) -> float:
        if self.scene_scale:
            return float(self.scene_scale)
        poses = [k.view.pose for k in self.keyframes]
        if len(poses) >= 3:
            c = cameras_convergence_point(poses)
            d = float(np.dot(c - kf.view.pose.t, kf.view.pose.forward))
            if np.isfinite(d) and d > 0:
                return d
        return 0.0

    def _overlap(self, a: _Keyframe, b: _Keyframe, depth: float) -> float:
        """Fraction of a 5x5 grid of a's image at ``depth`` that b sees in front of it."""
        cam = a.view.camera
        u = np.linspace(0.1, 0.9, 5) * (cam.width - 1)
        v = np.linspace(0.1, 0.9, 5) * (cam.height - 1)
        uu, vv = np.meshgrid(u, v)
        ray = np.stack([(uu.ravel() - cam.cx) / cam.fx, (vv.ravel() - cam.cy) / cam.fy,
                        np.ones(uu.size)], 1)
        pts = (ray * depth) @ a.view.pose.R.T + a.view.pose.t
        pc = pts @ b.R_cw.T + b.t_cw
        cb = b.view.camera
        ok = pc[:, 2] > 1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            ub = cb.fx * pc[:, 0] / pc[:, 2] + cb.cx
            vb = cb.fy * pc[:, 1] / pc[:, 2] + cb.cy
        ok &= (ub >= 0) & (ub < cb.width) & (vb >= 0) & (vb < cb.height)
        return float(ok.mean())

    def _pairs(self, kf: _Keyframe) -> list[int]:
        cfg = self.config
        n = len(self.keyframes)
        seq = list(range(max(0, n - cfg.sequential_pairs), n))
        depth = self._depth_guess(kf)
        others = [i for i in range(n) if i not in seq]
        if depth > 0 and others and cfg.overlap_pairs > 0:
            scores = [(self._overlap(kf, self.keyframes[i], depth), i) for i in others]
            scores = [s for s in scores if s[0] >= cfg.min_overlap]
            scores.sort(key=lambda s: (-s[0], s[1]))
            seq += [i for _, i in scores[:cfg.overlap_pairs]]
        return seq

    # -- matching -----------------------------------------------------------------------------
    def _match(self, a: _Keyframe, b: _Keyframe) -> tuple[np.ndarray, np.ndarray]:
        """Verified matches [m,2] (feature index in a, in b) and their descriptor distances."""
        cfg = self.config
        none = (np.zeros((0, 2), int), np.zeros(0))
        if len(a.desc) < 2 or len(b.desc) < 2:
            return none
        import torch  # top-k on the similarity matrix: ~2x faster than numpy argpartition

        da = torch.from_numpy(a.desc.astype(np.float32))
        db = torch.from_numpy(b.desc.astype(np.float32))
        da = torch.nn.functional.normalize(da, dim=1)
        db = torch.nn.functional.normalize(db, dim=1)
        sim = da @ db.T
        R = b.R_cw @ a.R_cw.T
        t = b.t_cw - R @ a.t_cw
        E = _skew(t) @ R
        f = 0.5 * (a.view.camera.fx + b.view.camera.fx)
        m, d, best = self._ratio_matches(sim, a.xn, b.xn, E, f)
        if cfg.epipolar_band_matching and len(m) >= cfg.min_inliers:
            # the same test among the candidates near each epipolar line only; a band match
            # must be as close in descriptor space as the pair's global matches mostly are
            # (a lone candidate on the line always passes the ratio test). Rows whose best
            # candidate anywhere is farther than that cannot give one: left out (exact, and the
            # band then costs a fraction of the full [na, nb] product)
            cap = float(np.quantile(d, cfg.guided_desc_quantile))
            rows = np.nonzero(best >= 1.0 - 0.5 * cap * cap)[0]
            band = self._epipolar_band(a.xn[rows], b.xn, E, f)
            sub = sim[torch.from_numpy(rows)].masked_fill_(~band, -2.0)
            mb, db_, _ = self._ratio_matches(sub, a.xn[rows], b.xn, E, f)
            mb[:, 0] = rows[mb[:, 0]]
            keep = (db_ <= cap) & ~np.isin(mb[:, 0], m[:, 0]) & ~np.isin(mb[:, 1], m[:, 1])
            m, d = np.r_[m, mb[keep]], np.r_[d, db_[keep]]
        if len(m) < cfg.min_inliers:
            return none
        return m, d

    def _ratio_matches(self, sim, xa: np.ndarray, xb: np.ndarray, E: np.ndarray, f: float
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ratio-tested, mutual, epipolar-verified matches [m,2] of a [na, nb] similarity
        matrix, their descriptor distances, and every row's best similarity."""
        import torch
        cfg = self.config
        top, idx = torch.topk(sim, 2, dim=1)
        # mutual check against each column's maximum: amax over dim 0 is ~20x cheaper than
        # argmax over dim 0 (a strided reduction) and equal up to exact ties
        col_best = sim.amax(dim=0).numpy()
        top = top.numpy()
        d_ab = np.sqrt(np.maximum(2.0 - 2.0 * top.astype(np.float64), 0.0))
        best_b = idx[:, 0].numpy()
        ratio_ok = d_ab[:, 0] < cfg.ratio * d_ab[:, 1]
        mutual = top[:, 0] >= col_best[best_b]
        idx_a = np.nonzero(ratio_ok & mutual & (top[:, 0] > -1.5))[0]
        idx_b = best_b[idx_a]
        # epipolar check with the known relative pose (normalised coords, Sampson -> pixels)
        ok = _sampson_px(xa[idx_a], xb[idx_b], E, f) < cfg.epipolar_px
        return np.stack([idx_a[ok], idx_b[ok]], 1), d_ab[idx_a[ok], 0], top[:, 0]

    def _epipolar_band(self, xa: np.ndarray, xb: np.ndarray, E: np.ndarray, f: float):
        """[na, nb] torch bool: pairs within ``epipolar_px`` (Sampson distance) of each other's
        epipolar line (float32: ~16M pairs at 4096 features a keyframe)."""
        import torch
        x1 = torch.from_numpy(np.c_[xa, np.ones(len(xa))].astype(np.float32))
        x2 = torch.from_numpy(np.c_[xb, np.ones(len(xb))].astype(np.float32))
        Et = torch.from_numpy(E.astype(np.float32))
        Ex1 = x1 @ Et.T  # [na,3] lines in b
        Etx2 = x2 @ Et  # [nb,3] lines in a
        num = (Ex1 @ x2.T).square_()
        den = (Ex1[:, :2].square().sum(1, keepdim=True) + Etx2[:, :2].square().sum(1)[None, :])
        return num < den.clamp_(min=1e-18).mul_((self.config.epipolar_px / f) ** 2)

    # -- public -------------------------------------------------------------------------------
    def add_keyframe(self, view: View, features: Optional[KeyframeFeatures] = None) -> dict:
        """Extract, pair, match and merge tracks for one keyframe; returns per-step stats.

        ``features``: the keyframe's ``KeyframeFeatures`` computed elsewhere (a worker process,
        ``sfm.prefetch``) with the same config; None extracts them here. Either way the
        result is the same. Thread-safe against ``cloud`` and ``report``.
        """
        with self._lock:
            return self._add_keyframe(view, features)

    def _add_keyframe(self, view: View, features: Optional[KeyframeFeatures]) -> dict:
        _check_view(view)
        if self.keyframes and view.stamp_ns < self.keyframes[-1].view.stamp_ns:
            self.counts["dropped_stamp_backwards"] += 1
            LOG.warning("keyframe %s dropped: stamp goes backwards", view.key)
            return {"dropped": "stamp_backwards"}
        t0 = time.perf_counter()
        if features is None:
            features = self.extract(view)
            extract_s = time.perf_counter() - t0
        else:
            extract_s = features.extract_s  # spent elsewhere, in parallel with this thread
        xy, desc, rgb = features.xy, features.desc, features.rgb
        if len(xy) == 0:
            self.counts["keyframes_without_features"] += 1
            LOG.warning("keyframe %s: no SIFT features (textureless or out of focus)", view.key)
        R_cw, t_cw = view.pose.world_to_cam()
        kf = _Keyframe(view, xy, undistort_normalized(xy, view.camera), desc, rgb,
                       self._n_features, R_cw, t_cw)
        self.tracks.add(len(xy))
        t1 = time.perf_counter()
        pairs = self._pairs(kf)
        n_matches = 0
        match_d = []
        for i in pairs:
            m, d = self._match(self.keyframes[i], kf)
            self.counts["pairs"] += 1
            if len(m) == 0:
                self.counts["pairs_without_matches"] += 1
                continue
            n_matches += len(m)
            match_d.append(d)
            oa = self.keyframes[i].offset
            for a, b in m:
                self.tracks.union(oa + int(a), kf.offset + int(b))
        self._n_features += len(xy)
        self.keyframes.append(kf)
        n_guided = 0
        if self.config.guided_matching and match_d:
            self._refresh()  # the points as of this keyframe's descriptor matches
            n_guided = self._guided_matches(len(self.keyframes) - 1, np.concatenate(match_d))
        t2 = time.perf_counter()
        self.times["features_s"] += extract_s
        self.times["matching_s"] += t2 - t1
        self.counts["keyframes"] += 1
        self.counts["verified_matches"] += n_matches
        self.counts["guided_matches"] += n_guided
        return {"key": view.key, "features": int(len(xy)),
                "sift_first_octave": features.first_octave,
                "pairs": len(pairs),
                "verified_matches": int(n_matches), "guided_matches": int(n_guided),
                "features_s": extract_s, "matching_s": t2 - t1}

    def _guided_matches(self, k: int, match_d: np.ndarray) -> int:
        """Extend known points into keyframe ``k`` by projection (guided matching).

        A point triangulated from earlier keyframes that projects within ``max_reproj_px`` of a
        still unmatched keypoint of ``k``, whose descriptor is as close to one of the track's
        descriptors as this keyframe's own verified matches are (``guided_desc_quantile`` of
        their distances), joins that track. The pose-selected pairs see only a few keyframes;
        this lets a point seen earlier grow its track in every later keyframe that sees it,
        while an epipolar-line mismatch (a wrong 3D point) finds no keypoint where it projects.
        """
        from scipy.spatial import cKDTree

        cfg = self.config
        kf = self.keyframes[k]
        items = [(r, v) for r, v in self._tri.items() if v is not None and v[2][-1] != k]
        if not items or len(kf.xn) == 0 or len(match_d) < cfg.min_inliers:
            return 0
        X = np.stack([v[0] for _, v in items])
        pc = X @ kf.R_cw.T + kf.t_cw
        front = pc[:, 2] > 1e-9
        cam = kf.view.camera
        px = np.array([cam.fx, cam.fy])
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = pc[:, :2] / pc[:, 2:3] * px
        uv = np.where(front[:, None] & np.isfinite(uv), uv, 1e12)
        dist, j = cKDTree(kf.xn * px).query(uv, k=1, distance_upper_bound=cfg.max_reproj_px)
        cand = np.nonzero(np.isfinite(dist))[0]
        if len(cand) == 0:
            return 0
        j = j[cand]
        gid = kf.offset + j
        free = np.array([self.tracks.parent[g] == g and g not in self.tracks.members
                         for g in gid.tolist()], bool)
        cand, j, gid = cand[free], j[free], gid[free]
        if len(cand) == 0:
            return 0
        # descriptor distance of the keypoint to the closest descriptor of the track
        mem = [items[c][1][1] for c in cand]
        lens = np.array([len(m) for m in mem])
        fids = np.concatenate(mem)
        owner = self._feature_owner(fids)
        dm = np.empty((len(fids), 128), np.float32)
        for o in np.unique(owner):
            sel = owner == o
            dm[sel] = self.keyframes[o].desc[fids[sel] - self.keyframes[o].offset]
        dm /= np.maximum(np.linalg.norm(dm, axis=1, keepdims=True), 1e-12)
        dk = kf.desc[j].astype(np.float32)
        dk /= np.maximum(np.linalg.norm(dk, axis=1, keepdims=True), 1e-12)
        d = np.linalg.norm(dm - np.repeat(dk, lens, axis=0), axis=1)
        ptr = np.r_[0, np.cumsum(lens)[:-1]]
        dmin = np.minimum.reduceat(d, ptr)
        ok = dmin <= np.quantile(match_d, cfg.guided_desc_quantile)
        cand, gid, dmin = cand[ok], gid[ok], dmin[ok]
        order = np.argsort(dmin, kind="stable")  # a keypoint claimed twice: the closer wins
        _, first = np.unique(gid[order], return_index=True)
        for c in order[first]:
            self.tracks.union(items[cand[c]][0], int(gid[c]))
        return len(first)

    def _feature_owner(self, fids: np.ndarray) -> np.ndarray:
        offs = np.array([k.offset for k in self.keyframes])
        return np.searchsorted(offs, fids, side="right") - 1

    def _triangulate(self, roots: list[int]) -> None:
        """(Re)triangulate the tracks ``roots`` and store results in ``self._tri``."""
        cfg = self.config
        if not roots:
            return
        Ps = np.stack([np.c_[k.R_cw, k.t_cw] for k in self.keyframes])  # [K,3,4]
        centers = np.stack([k.view.pose.t for k in self.keyframes])
        offs = np.array([k.offset for k in self.keyframes])
        xn_all = np.concatenate([k.xn for k in self.keyframes])
        fx = np.array([k.view.camera.fx for k in self.keyframes])
        # group tracks by length for batched DLT
        tracks = []
        for r in roots:
            mem = np.array(sorted(self.tracks.members.get(r, [r])))
            kfi = np.searchsorted(offs, mem, side="right") - 1
            _, first = np.unique(kfi, return_index=True)  # one observation per keyframe
            if len(first) < len(kfi):
                self.counts["track_conflicts"] += 1
            tracks.append((r, mem[first], kfi[first]))
        for r, mem, kfi in tracks:
            self._tri[r] = None
        for _round in range(2):
            by_len: dict[int, list] = {}
            for item in tracks:
                if len(item[1]) >= max(2, cfg.min_track_length):
                    by_len.setdefault(len(item[1]), []).append(item)
            retry = []
            for L, items in by_len.items():
                mems = np.stack([it[1] for it in items])  # [T,L]
                kfs = np.stack([it[2] for it in items])
                x = xn_all[mems]  # [T,L,2]
                P = Ps[kfs]  # [T,L,3,4]
                A = np.concatenate([x[..., 0:1] * P[:, :, 2] - P[:, :, 0],
                                    x[..., 1:2] * P[:, :, 2] - P[:, :, 1]], axis=1)
                _, _, vt = np.linalg.svd(A)
                Xh = vt[:, -1]
                with np.errstate(divide="ignore", invalid="ignore"):
                    X = Xh[:, :3] / Xh[:, 3:4]
                    for _ in range(cfg.refine_iters):
                        X = _gauss_newton_step(X, P, x)
                pc = np.einsum("tlij,tj->tli", P[..., :3], X) + P[..., 3]
                z = pc[..., 2]
                with np.errstate(divide="ignore", invalid="ignore"):
                    proj = pc[..., :2] / z[..., None]
                err = np.linalg.norm(proj - x, axis=2) * fx[kfs]  # [T,L] pixels
                err = np.where(np.isfinite(err) & (z > 0), err, np.inf)
                for j, (r, mem, kfi) in enumerate(items):
                    e = err[j]
                    bad = e > cfg.max_reproj_px
                    if bad.any():
                        if _round == 0 and (~bad).sum() >= max(2, cfg.min_track_length):
                            retry.append((r, mem[~bad], kfi[~bad]))
                        continue
                    if not np.all(np.isfinite(X[j])):
                        continue
                    rays = X[j] - centers[kfi]
                    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
                    cosm = np.clip(rays @ rays.T, -1, 1).min()
                    if np.degrees(np.arccos(cosm)) < cfg.min_tri_angle_deg:
                        continue
                    self._tri[r] = (X[j], mem, kfi, float(e.mean()))
            tracks = retry
            if not tracks:
                break

    def _refresh(self) -> None:
        """Triangulate the tracks changed since the last refresh; forget merged-away roots."""
        t0 = time.perf_counter()
        dirty = [r for r in self.tracks.dirty if self.tracks.find(r) == r]
        self.tracks.dirty.clear()
        for r in list(self._tri):
            if self.tracks.find(r) != r:
                del self._tri[r]
        self._triangulate(dirty)
        self.times["triangulation_s"] += time.perf_counter() - t0

    def cloud(self, conditioned: Optional[bool] = None) -> SfmCloud:
        """The current cloud (triangulates the tracks changed since the last call).

        ``conditioned`` (default: ``config.conditioned_two_view``) keeps only the 2-view points
        that are about as well conditioned as the multi-view ones (position uncertainty, see
        ``_uncertainty``, and reprojection error compared with the multi-view points' by the
        config's quantiles): a wrong match along the epipolar line passes the epipolar check
        but tends to lie under a narrow angle or fit its rays worse. ``False`` returns every
        triangulated point. Thread-safe against ``add_keyframe``.
        """
        with self._lock:
            return self._cloud(conditioned)

    def _cloud(self, conditioned: Optional[bool]) -> SfmCloud:
        self._refresh()
        if conditioned is None:
            conditioned = self.config.conditioned_two_view
        views = [k.view for k in self.keyframes]
        pts = [(r, v) for r, v in sorted(self._tri.items()) if v is not None]
        if conditioned and pts:
            cfg = self.config
            lens = np.array([len(v[1]) for _, v in pts])
            multi = lens >= 3
            if multi.any() and not multi.all():
                unc = self._uncertainty([v[0] for _, v in pts], [v[2] for _, v in pts])
                # mean residual per observation, corrected for the residual's degrees of
                # freedom (2L measurements - 3 unknowns): a 2-view point fits its rays more
                # closely than a 3-view one with the same image noise
                err = np.array([v[3] for _, v in pts]) / np.sqrt((2 * lens - 3) / (2 * lens))
                keep = multi | (
                    (unc <= np.quantile(unc[multi], cfg.two_view_uncertainty_quantile))
                    & (err <= np.quantile(err[multi], cfg.two_view_residual_quantile)))
                self.counts["two_view_points_withheld"] = int((~keep).sum())
                pts = [p for p, k in zip(pts, keep) if k]
        if not pts:
            return SfmCloud.empty(views)
        xy_all = np.concatenate([k.xy for k in self.keyframes])
        rgb_all = np.concatenate([k.rgb for k in self.keyframes]).astype(float)
        xyz = np.stack([v[0] for _, v in pts])
        lens = np.array([len(v[1]) for _, v in pts])
        ptr = np.zeros(len(pts) + 1, np.int64)
        np.cumsum(lens, out=ptr[1:])
        mem = np.concatenate([v[1] for _, v in pts])
        ov = np.concatenate([v[2] for _, v in pts]).astype(np.int32)
        rgb = np.add.reduceat(rgb_all[mem], ptr[:-1], axis=0) / lens[:, None]
        err = np.array([v[3] for _, v in pts])
        return SfmCloud(xyz, np.clip(np.round(rgb), 0, 255).astype(np.uint8), err, ptr, ov,
                        xy_all[mem].astype(np.float32), views)

    def _uncertainty(self, xyz: list, kfis: list) -> np.ndarray:
        """Position uncertainty of each point per unit of normalised image noise.

        Each observation at distance d along unit ray r constrains the two directions across r
        with weight 1/d^2; the uncertainty is the point's least-constrained direction,
        1/sqrt(smallest eigenvalue of sum_i (I - r_i r_i^T) / d_i^2) (world units per radian
        of image error). A 2-view point seen under a narrow angle is long along its rays and
        gets a large value; a long track under wide angles a small one.
        """
        centers = np.stack([k.view.pose.t for k in self.keyframes])
        lens = np.array([len(k) for k in kfis])
        X = np.repeat(np.stack(xyz), lens, axis=0)
        ray = X - centers[np.concatenate(kfis)]
        d2 = np.maximum(np.einsum("ij,ij->i", ray, ray), 1e-30)
        r = ray / np.sqrt(d2)[:, None]
        info = (np.eye(3)[None] - r[:, :, None] * r[:, None, :]) / d2[:, None, None]
        ptr = np.r_[0, np.cumsum(lens)[:-1]]
        A = np.add.reduceat(info.reshape(-1, 9), ptr, axis=0).reshape(-1, 3, 3)
        lam = np.linalg.eigvalsh(A)[:, 0]
        return 1.0 / np.sqrt(np.maximum(lam, 1e-30))

    def report(self) -> dict:
        """Counts and time per step so far."""
        with self._lock:
            return self._report()

    def _report(self) -> dict:
        return {"keyframes": len(self.keyframes), "counts": dict(self.counts),
                "times_s": {k: round(v, 4) for k, v in self.times.items()},
                "tracks_triangulated": sum(v is not None for v in self._tri.values())}
