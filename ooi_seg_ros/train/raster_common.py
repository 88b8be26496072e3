"""Shared pieces of the rasterisers: cameras, EWA projection, SH colour, per-pixel alpha.

Both the tile rasteriser (raster_cpu) and the brute-force reference (raster_reference) use
these functions, so a difference between the two isolates the tiling/sorting/compositing.
Pixel convention: ROS/OpenCV, pixel (row i, column j) has its centre at (u=j, v=i).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from ..core.types import CameraIntrinsics, Pose

LOWPASS = 0.3  # added to the 2D covariance diagonal (pixel^2), as in 3DGS
ALPHA_MIN = 1.0 / 255.0  # contributions below this are skipped
ALPHA_MAX = 0.99  # alpha is clamped so transmittance never reaches zero
T_MIN = 1e-4  # early termination: stop once transmittance would fall below this
NEAR = 0.01  # Gaussians closer than this (metres, camera z) are culled

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


@dataclass
class RasterCamera:
    """A pinhole camera for rendering: world-to-camera R, t (OpenCV optical frame), K, size."""

    R: torch.Tensor  # [3, 3] world -> camera rotation
    t: torch.Tensor  # [3] world -> camera translation
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    lowpass: float = LOWPASS  # pixel^2 added to every 2D covariance's diagonal (see LOWPASS)

    @staticmethod
    def from_view(camera: CameraIntrinsics, pose: Pose, dtype: torch.dtype = torch.float32,
                  device: str = "cpu", lowpass: float = LOWPASS) -> "RasterCamera":
        R, t = pose.world_to_cam()
        return RasterCamera(torch.as_tensor(np.asarray(R), dtype=dtype, device=device),
                            torch.as_tensor(np.asarray(t), dtype=dtype, device=device),
                            float(camera.fx), float(camera.fy), float(camera.cx),
                            float(camera.cy), int(camera.width), int(camera.height),
                            float(lowpass))

    @property
    def center(self) -> torch.Tensor:  # [3] camera centre in the world
        return -self.R.T @ self.t

    def to(self, dtype: torch.dtype) -> "RasterCamera":
        return RasterCamera(self.R.to(dtype), self.t.to(dtype), self.fx, self.fy, self.cx,
                            self.cy, self.width, self.height, self.lowpass)


@dataclass
class Projected:
    """Per-Gaussian screen-space quantities for one camera."""

    means2d: torch.Tensor  # [N, 2] pixel coords (u, v)
    conics: torch.Tensor  # [N, 3] inverse 2D covariance (a, b, c): [[a, b], [b, c]]
    depths: torch.Tensor  # [N] camera z
    radii: torch.Tensor  # [N] int64 3-sigma radius in pixels, 0 = culled
    colors: torch.Tensor  # [N, 3] view-dependent colour (SH + 0.5, clamped at 0)
    opacities: torch.Tensor  # [N]


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """[N, 4] (w, x, y, z), any norm -> [N, 3, 3] rotation matrices."""
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(-1, 3, 3)


def covariance_3d(log_scales: torch.Tensor, quats: torch.Tensor) -> torch.Tensor:
    """Sigma = R S S^T R^T, [N, 3, 3]."""
    M = quat_to_rotmat(quats) * torch.exp(log_scales)[:, None, :]
    return M @ M.transpose(1, 2)


def eval_sh(degree: int, sh_dc: torch.Tensor, sh_rest: torch.Tensor,
            dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate real SH (reference 3DGS basis) up to ``degree``; returns RGB + 0.5, >= 0."""
    res = SH_C0 * sh_dc
    if degree > 0:
        d = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        x, y, z = d[:, 0:1], d[:, 1:2], d[:, 2:3]
        r = sh_rest
        res = res - SH_C1 * y * r[:, 0] + SH_C1 * z * r[:, 1] - SH_C1 * x * r[:, 2]
        if degree > 1:
            xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
            res = (res + SH_C2[0] * xy * r[:, 3] + SH_C2[1] * yz * r[:, 4]
                   + SH_C2[2] * (2 * zz - xx - yy) * r[:, 5] + SH_C2[3] * xz * r[:, 6]
                   + SH_C2[4] * (xx - yy) * r[:, 7])
            if degree > 2:
                res = (res + SH_C3[0] * y * (3 * xx - yy) * r[:, 8]
                       + SH_C3[1] * xy * z * r[:, 9]
                       + SH_C3[2] * y * (4 * zz - xx - yy) * r[:, 10]
                       + SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy) * r[:, 11]
                       + SH_C3[4] * x * (4 * zz - xx - yy) * r[:, 12]
                       + SH_C3[5] * z * (xx - yy) * r[:, 13]
                       + SH_C3[6] * x * (xx - 3 * yy) * r[:, 14])
    return torch.clamp_min(res + 0.5, 0.0)


def project(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
            logit_opacities: torch.Tensor, sh_dc: torch.Tensor, sh_rest: torch.Tensor,
            cam: RasterCamera, sh_degree: int,
            colors_override: Optional[torch.Tensor] = None) -> Projected:
    """EWA splatting: camera-space means, Jacobian of the perspective map, 2D covariance.

    A Gaussian is culled (radius 0) when it is behind the near plane, its 2D covariance is
    degenerate or its 3-sigma square lies entirely outside the image.
    """
    pc = means @ cam.R.T + cam.t
    z = pc[:, 2]
    zc = z.clamp_min(NEAR)
    # clamp the direction used in the Jacobian (as the reference does) so Gaussians far
    # outside the frustum do not get huge, unstable footprints
    limx = 1.3 * max(cam.cx, cam.width - cam.cx) / cam.fx
    limy = 1.3 * max(cam.cy, cam.height - cam.cy) / cam.fy
    tx = (pc[:, 0] / zc).clamp(-limx, limx)
    ty = (pc[:, 1] / zc).clamp(-limy, limy)
    zero = torch.zeros_like(zc)
    J = torch.stack([cam.fx / zc, zero, -cam.fx * tx / zc,
                     zero, cam.fy / zc, -cam.fy * ty / zc], -1).reshape(-1, 2, 3)
    cov3 = covariance_3d(log_scales, quats)
    JW = J @ cam.R
    cov2 = JW @ cov3 @ JW.transpose(1, 2)
    a = cov2[:, 0, 0] + cam.lowpass
    b = cov2[:, 0, 1]
    c = cov2[:, 1, 1] + cam.lowpass
    det = a * c - b * b
    ok_det = det > 1e-12
    det_s = torch.where(ok_det, det, torch.ones_like(det))
    conics = torch.stack([c / det_s, -b / det_s, a / det_s], -1)
    u = cam.fx * pc[:, 0] / zc + cam.cx
    v = cam.fy * pc[:, 1] / zc + cam.cy
    means2d = torch.stack([u, v], -1)
    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt(torch.clamp_min(mid * mid - det, 0.1))
        radii = torch.ceil(3.0 * torch.sqrt(lam)).to(torch.int64)
        inside = ((u + radii > -0.5) & (u - radii < cam.width - 0.5)
                  & (v + radii > -0.5) & (v - radii < cam.height - 0.5))
        keep = (z > NEAR) & ok_det & inside & torch.isfinite(u) & torch.isfinite(v)
        radii = torch.where(keep, radii, torch.zeros_like(radii))
    if colors_override is not None:
        colors = colors_override
    else:
        dirs = means - cam.center
        colors = eval_sh(sh_degree, sh_dc, sh_rest, dirs)
    return Projected(means2d, conics, z, radii, colors, torch.sigmoid(logit_opacities))


def pixel_alpha(dx: torch.Tensor, dy: torch.Tensor, conics: torch.Tensor,
                opac: torch.Tensor) -> torch.Tensor:
    """alpha = min(0.99, o * exp(-0.5 d^T conic d)), zero below 1/255 or for power > 0.

    ``dx``, ``dy`` are pixel minus mean; ``conics`` [..., 3] and ``opac`` [...] broadcast.
    """
    power = (-0.5 * (conics[..., 0] * dx * dx + conics[..., 2] * dy * dy)
             - conics[..., 1] * dx * dy)
    alpha = torch.clamp_max(opac * torch.exp(torch.clamp_max(power, 0.0)), ALPHA_MAX)
    keep = (power <= 0) & (alpha >= ALPHA_MIN)
    return alpha * keep


@dataclass
class RenderOutput:
    """A rendered view."""

    image: torch.Tensor  # [H, W, 3] composited over the background
    alpha: torch.Tensor  # [H, W] accumulated opacity (1 - final transmittance)
    radii: torch.Tensor  # [N] int64, 0 = not drawn in this view
    n_intersections: int = 0  # Gaussian-tile pairs (tile rasteriser) or drawn Gaussians
