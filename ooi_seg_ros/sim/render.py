"""CPU ray-cast rendering of a SimScene with Open3D's RaycastingScene.

Per sample: first hit -> triangle -> material texture of the world-space hit point x light
(hemisphere ambient + Lambert with a cast shadow), sky for misses. With supersampling the
colour is the mean of the sub-samples (adaptive: textured once where all sub-samples see the
same part) and the mask holds the pixels where at least half of the sub-samples hit the OOI.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import open3d as o3d

from ..core.types import CameraIntrinsics, Pose
from .materials import shade_material, sky_color
from .scene import SimScene

INDOOR_FILL = (0.55, 0.55, 0.57)  # colour of a ray that leaves a closed room (should not happen)


@dataclass
class RenderResult:
    """One rendered view."""

    rgb: np.ndarray  # [H, W, 3] uint8
    mask: np.ndarray  # [H, W] bool, first hit is the OOI in >= half of the sub-samples
    depth: np.ndarray  # [H, W] float32 optical-axis depth (nearest sub-sample on edges), inf=sky


def intrinsics_from_fov(width: int, height: int, hfov_deg: float,
                        distortion: Optional[Sequence[float]] = None) -> CameraIntrinsics:
    """Square-pixel pinhole intrinsics with horizontal field of view ``hfov_deg``.

    The principal point is the image centre in the ROS/OpenCV convention (pixel centres at
    integer coordinates): cx = (W - 1) / 2. ``distortion`` = plumb_bob (k1, k2, p1, p2, k3)
    coefficients as in ROS CameraInfo (None or all zero: an ideal pinhole).
    """
    fx = (width / 2.0) / np.tan(np.radians(hfov_deg) / 2.0)
    cam = CameraIntrinsics(int(width), int(height), float(fx), float(fx),
                           (width - 1) / 2.0, (height - 1) / 2.0)
    if distortion is not None and np.any(np.asarray(distortion, float) != 0):
        d = np.zeros(5)
        vals = np.asarray(distortion, float).reshape(-1)
        if len(vals) > 5:
            raise ValueError(f"distortion {list(vals)}: give at most 5 plumb_bob coefficients")
        d[: len(vals)] = vals
        cam.distortion_model = "plumb_bob"
        cam.dist = d
    return cam


def camera_rays(cam: CameraIntrinsics, pose: Pose, ss: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Unit ray directions [H, W, ss*ss, 3] (world) and their camera-z [H, W, ss*ss].

    Sub-samples sit on a regular ss x ss grid inside each pixel (centred on the pixel centre).
    """
    offs = (np.arange(ss) + 0.5) / ss - 0.5
    oy, ox = np.meshgrid(offs, offs, indexing="ij")
    us = np.arange(cam.width, dtype=np.float64)
    vs = np.arange(cam.height, dtype=np.float64)
    u = us[None, :, None] + ox.reshape(1, 1, -1)
    v = vs[:, None, None] + oy.reshape(1, 1, -1)
    x = (u - cam.cx) / cam.fx
    y = (v - cam.cy) / cam.fy
    x, y = np.broadcast_arrays(x, y)
    if cam.has_distortion:
        x, y = undistort_normalized(x, y, cam)
    d = np.stack([x, y, np.ones_like(x)], -1)
    norm = np.linalg.norm(d, axis=-1)
    d = d / norm[..., None]
    zc = 1.0 / norm  # camera-z component of the unit ray
    return d @ pose.R.T, zc


def _plumb_bob(dist: np.ndarray) -> tuple[float, float, float, float, float]:
    k = np.zeros(5)
    k[: min(len(dist), 5)] = np.asarray(dist, float)[:5]
    return tuple(float(x) for x in k)  # k1, k2, p1, p2, k3


def distort_normalized(x: np.ndarray, y: np.ndarray,
                       cam: CameraIntrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Apply the camera's plumb_bob distortion to normalized image coordinates."""
    if not cam.has_distortion:
        return x, y
    if cam.distortion_model != "plumb_bob":
        raise ValueError(f"the simulator renders only plumb_bob distortion, not "
                         f"{cam.distortion_model!r}")
    k1, k2, p1, p2, k3 = _plumb_bob(cam.dist)
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def undistort_normalized(xd: np.ndarray, yd: np.ndarray, cam: CameraIntrinsics,
                         iterations: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Invert ``distort_normalized`` by fixed-point iteration (as OpenCV does)."""
    if not cam.has_distortion:
        return xd, yd
    if cam.distortion_model != "plumb_bob":
        raise ValueError(f"the simulator renders only plumb_bob distortion, not "
                         f"{cam.distortion_model!r}")
    k1, k2, p1, p2, k3 = _plumb_bob(cam.dist)
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = (xd - dx) / radial
        y = (yd - dy) / radial
    return x, y


# std (px) of the optical low-pass before a Bayer mosaic (``Renderer.render(demosaic=True)``):
# a modulation of exp(-2 pi^2 0.6^2 0.5^2) = 0.17 at the pixel's Nyquist frequency, before the
# pixel's own area -- a camera's lens and anti-aliasing filter pass 0.1-0.3 there
BAYER_PSF_PX = 0.6


def _bayer_demosaic(img: np.ndarray, rng: Optional[np.random.Generator],
                    sensor_noise: float) -> np.ndarray:
    """uint8 RGB a camera delivers of the linear image ``img`` [h, w, 3] (0-255): the lens's
    and the sensor's optical low-pass first (a Gaussian of ``BAYER_PSF_PX``), then the RGGB
    mosaic's one value per pixel, with Gaussian noise of std ``sensor_noise`` (from ``rng``;
    none without one), 8-bit, then OpenCV's edge-aware demosaicing (``BayerBG`` is OpenCV's
    name for the RGGB layout). Without the low-pass the renders' point-sampled texture, whose
    detail reaches the pixel, would alias into colour moire no camera shows."""
    import cv2
    img = cv2.GaussianBlur(np.ascontiguousarray(img, np.float32), (0, 0), BAYER_PSF_PX,
                           borderType=cv2.BORDER_REFLECT)
    raw = np.empty(img.shape[:2], np.float32)
    raw[0::2, 0::2] = img[0::2, 0::2, 0]
    raw[0::2, 1::2] = img[0::2, 1::2, 1]
    raw[1::2, 0::2] = img[1::2, 0::2, 1]
    raw[1::2, 1::2] = img[1::2, 1::2, 2]
    if rng is not None and sensor_noise > 0:
        raw = raw + rng.normal(0.0, sensor_noise, raw.shape)
    raw8 = np.clip(np.round(raw), 0, 255).astype(np.uint8)
    return cv2.cvtColor(raw8, cv2.COLOR_BayerBG2RGB_EA)


class Renderer:
    """Renders views of one scene; cheap to create, holds no per-view state."""

    def __init__(self, scene: SimScene) -> None:
        self.scene = scene
        self.V = scene._get("V")
        self.F = scene._get("F")
        self.N = scene._get("N")
        self.tri_mat = scene._get("tri_material")
        self.tri_ooi = scene._get("tri_ooi")
        self.tri_part = scene._get("tri_part")
        self.mat_names = scene._get("material_names")
        self.noise = scene.noise()
        self.rs = scene.raycaster("all")
        self.casters = scene.raycaster("casters")
        L = np.asarray(scene.lighting.direction, np.float32)
        self.L = L / np.linalg.norm(L)
        self.eps = 1e-4 * max(scene.ooi_diagonal, 1e-3)
        self._ray_cache: dict = {}

    def render(self, cam: CameraIntrinsics, pose: Pose, supersample: int = 2,
               rng: Optional[np.random.Generator] = None, sensor_noise: float = 1.5,
               exposure: float = 1.0, object_only: bool = False,
               shade_subsamples: bool = False, vignetting: float = 0.0,
               demosaic: bool = False) -> RenderResult:
        """Render the view ``pose`` (camera-to-world, optical frame) with intrinsics ``cam``.

        ``sensor_noise`` is the std of additive Gaussian pixel noise in 0-255 units (drawn from
        ``rng``; none without one), ``exposure`` a gain (auto-exposure varies per frame).
        ``object_only``: every sub-sample that does not see the OOI is black, so an outline
        pixel holds coverage x object colour -- what an object-only model composited over black
        should render (shadows the rest of the scene casts on the object stay).
        ``vignetting``: the lens's light falloff, a gain 1 - vignetting * r^2 with r the distance
        from the principal point over the half diagonal (the corners darkest; 0 = none).
        ``demosaic``: the lens low-passes the image (``BAYER_PSF_PX``), the sensor records one
        colour per pixel (an RGGB Bayer mosaic, the noise drawn on it) and the image is
        OpenCV's edge-aware demosaicing of it, as a camera delivers it -- the noise then
        correlated between neighbouring pixels and channels.
        ``shade_subsamples``: shade every sub-sample (the texture integrated over the pixel, as
        a camera does) instead of once per pixel whose sub-samples all hit the same part (the
        default, cheaper: texture detail finer than a pixel is then point-sampled).
        """
        ss = max(int(supersample), 1)
        S = ss * ss
        H, W = cam.height, cam.width
        key = (W, H, cam.fx, cam.fy, cam.cx, cam.cy, cam.distortion_model,
               tuple(np.asarray(cam.dist, float).tolist()), ss)
        if key not in self._ray_cache:  # camera-frame rays are the same for every pose
            dc, zc = camera_rays(cam, Pose.identity(), ss)
            self._ray_cache = {key: (dc.reshape(-1, 3).astype(np.float32), zc.reshape(-1))}
        dc, zc = self._ray_cache[key]
        d = dc @ np.asarray(pose.R, np.float32).T  # [H*W*S, 3], pixel-major
        o = np.broadcast_to(np.asarray(pose.t, np.float32), d.shape)
        rays = np.ascontiguousarray(np.concatenate([o, d], 1))
        ans = self.rs.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy()
        hit = np.isfinite(t)
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        prim[~hit] = 0
        part = np.where(hit, self.tri_part[prim], -1).reshape(-1, S)
        ooi = (hit & self.tri_ooi[prim]).reshape(-1, S)
        mask = ooi.mean(1) >= 0.5
        # Adaptive anti-aliasing: a pixel whose sub-samples all see the same part (or all the
        # sky) is shaded once at the mean of its sub-samples; only pixels on silhouettes and
        # part boundaries are shaded per sub-sample. Casting rays is cheap, texturing is not.
        coherent_geo = np.all(part == part[:, :1], axis=1)
        coherent = coherent_geo & (not shade_subsamples)
        p = o + np.where(hit, t, 0.0)[:, None] * d
        uv = ans["primitive_uvs"].numpy()
        f = self.F[prim]
        w0 = (1 - uv[:, 0] - uv[:, 1])[:, None]
        n = w0 * self.N[f[:, 0]] + uv[:, 0:1] * self.N[f[:, 1]] + uv[:, 1:2] * self.N[f[:, 2]]
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        back = np.einsum("ij,ij->i", n, d) > 0
        n[back] = -n[back]
        ci = np.nonzero(coherent)[0]
        ii = np.nonzero(~coherent)[0]
        sub = (ii[:, None] * S + np.arange(S)).reshape(-1)
        # shading samples: the coherent pixels' means, then every sub-sample of the others
        sp = np.concatenate([p.reshape(-1, S, 3)[ci].mean(1), p[sub]])
        sn = np.concatenate([n.reshape(-1, S, 3)[ci].mean(1), n[sub]])
        sn /= np.maximum(np.linalg.norm(sn, axis=1, keepdims=True), 1e-12)
        sd = np.concatenate([d.reshape(-1, S, 3)[ci].mean(1), d[sub]])
        sd /= np.linalg.norm(sd, axis=1, keepdims=True)
        sprim = np.concatenate([prim[ci * S], prim[sub]])
        shit = np.concatenate([hit[ci * S], hit[sub]])
        col = np.empty((len(sp), 3), np.float32)
        if object_only:
            shit = shit & self.tri_ooi[sprim]
            col[~shit] = 0.0
        elif np.any(~shit):
            if self.scene.indoor:
                col[~shit] = INDOOR_FILL
            else:
                col[~shit] = sky_color(self.scene.lighting, self.noise, sd[~shit])
        idx = np.nonzero(shit)[0]
        if len(idx):
            ps, ns = sp[idx], sn[idx]
            albedo = np.empty((len(idx), 3), np.float32)
            mats = self.tri_mat[sprim[idx]]
            for mi in np.unique(mats):
                sel = mats == mi
                mat = self.scene.materials[self.mat_names[mi]]
                albedo[sel] = shade_material(mat, self.noise, ps[sel], ns[sel])
            col[idx] = albedo * self._light(ps, ns)[:, None]
        img = np.empty((H * W, 3), np.float32)
        img[ci] = col[: len(ci)]
        img[ii] = col[len(ci):].reshape(-1, S, 3).mean(1)
        img = img.reshape(H, W, 3)
        mask = mask.reshape(H, W)
        depth_s = np.where(hit, t * zc, np.inf).reshape(-1, S)
        depth = np.where(coherent_geo, depth_s.mean(1), depth_s.min(1)).reshape(H, W)
        depth = depth.astype(np.float32)
        img = img * (exposure * 255.0)
        if vignetting > 0:
            yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
            r2 = ((xx + 0.5 - cam.cx) ** 2 + (yy + 0.5 - cam.cy) ** 2) / (0.25 * (W * W + H * H))
            img = img * (1.0 - float(vignetting) * r2)[..., None]
        if demosaic:
            return RenderResult(_bayer_demosaic(img, rng, sensor_noise), mask, depth)
        if rng is not None and sensor_noise > 0:
            img = img + rng.normal(0.0, sensor_noise, img.shape)
        rgb = np.clip(np.round(img), 0, 255).astype(np.uint8)
        return RenderResult(rgb, mask, depth)

    def _light(self, p: np.ndarray, n: np.ndarray) -> np.ndarray:
        """Light intensity [N] at points ``p`` with normals ``n`` (shadow rays to the light)."""
        lt = self.scene.lighting
        ndl = n @ self.L
        hemi = lt.ambient * (0.78 + 0.22 * n[:, 2])
        direct = lt.diffuse * np.clip(ndl, 0.0, None)
        lit = ndl > 0
        if lt.shadow > 0 and np.any(lit):
            li = np.nonzero(lit)[0]
            orig = p[li] + n[li] * self.eps * 10
            sr = np.concatenate([orig, np.broadcast_to(self.L, orig.shape)], 1)
            occ = np.isfinite(self.casters.cast_rays(
                o3d.core.Tensor(np.ascontiguousarray(sr, np.float32)))["t_hit"].numpy())
            direct[li[occ]] *= 1.0 - lt.shadow
        return (hemi + direct).astype(np.float32)
