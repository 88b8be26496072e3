"""Brute-force reference renderer: every drawn Gaussian at every pixel, sorted globally.

Plain torch, differentiable by autograd, O(N * H * W) memory: only for tests and benchmarks on
small scenes. It shares projection and alpha with the tile rasteriser, so comparing both checks
the tiling, per-tile sorting and compositing. Unlike the tile rasteriser it does not cut a
Gaussian at its 3-sigma square, so images agree to within the tail mass beyond 3 sigma.
"""

from __future__ import annotations

from typing import Optional

import torch

from .gaussians import GaussianModel
from .raster_common import (RasterCamera, RenderOutput, T_MIN, pixel_alpha, project)


def render(model: GaussianModel, cam: RasterCamera, background: torch.Tensor,
           sh_degree: Optional[int] = None) -> RenderOutput:
    """Render ``model`` from ``cam`` over ``background`` [3] (dense, for checking only)."""
    deg = model.sh_degree if sh_degree is None else sh_degree
    pr = project(model.means, model.log_scales, model.quats, model.logit_opacities,
                 model.sh_dc, model.sh_rest, cam, deg)
    H, W = cam.height, cam.width
    vis = torch.nonzero(pr.radii > 0).squeeze(1)
    order = vis[torch.argsort(pr.depths[vis].detach(), stable=True)]
    dt = model.means.dtype
    vv, uu = torch.meshgrid(torch.arange(H, dtype=dt), torch.arange(W, dtype=dt), indexing="ij")
    px = torch.stack([uu.reshape(-1), vv.reshape(-1)], -1)  # [P, 2]
    m2 = pr.means2d[order]
    dx = px[None, :, 0] - m2[:, None, 0]
    dy = px[None, :, 1] - m2[:, None, 1]
    alpha = pixel_alpha(dx, dy, pr.conics[order][:, None, :], pr.opacities[order][:, None])
    log_t = torch.cumsum(torch.log1p(-alpha), dim=0)  # inclusive transmittance (log)
    t_incl = torch.exp(log_t)
    t_excl = torch.exp(log_t - torch.log1p(-alpha))
    w = alpha * t_excl * (t_incl.detach() >= T_MIN)
    color = w.T @ pr.colors[order]  # [P, 3]
    acc = w.sum(0)
    img = color + (1.0 - acc)[:, None] * background.to(dt)[None, :]
    return RenderOutput(img.reshape(H, W, 3), acc.reshape(H, W), pr.radii, int(len(order)))
