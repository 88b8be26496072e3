"""gsplat (CUDA) back-end with the same interface as ``raster_cpu.render``.

Optional: used only when the ``gsplat`` package imports and CUDA is available. gsplat puts
pixel centres at +0.5, this package at integer coordinates (ROS/OpenCV), hence cx/cy + 0.5.
UNVERIFIED on a GPU in this project (no GPU was available); the comparison test skips
cleanly without CUDA.
"""

from __future__ import annotations

from typing import Optional

import torch

from .gaussians import GaussianModel
from .raster_common import LOWPASS, RasterCamera, RenderOutput


def gsplat_available() -> bool:
    """True when gsplat imports and a CUDA device is present."""
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return True


def render(model: GaussianModel, cam: RasterCamera, background: torch.Tensor,
           sh_degree: Optional[int] = None) -> RenderOutput:
    """Render with ``gsplat.rasterization`` on the model's (CUDA) device."""
    from gsplat import rasterization

    deg = model.sh_degree if sh_degree is None else sh_degree
    dev = model.means.device
    view = torch.eye(4, dtype=model.means.dtype, device=dev)
    view[:3, :3] = cam.R.to(dev, model.means.dtype)
    view[:3, 3] = cam.t.to(dev, model.means.dtype)
    K = torch.tensor([[cam.fx, 0.0, cam.cx + 0.5], [0.0, cam.fy, cam.cy + 0.5], [0.0, 0.0, 1.0]],
                     dtype=model.means.dtype, device=dev)
    sh = torch.cat([model.sh_dc[:, None, :], model.sh_rest], 1)
    colors, alphas, meta = rasterization(
        model.means, model.quats / model.quats.norm(dim=-1, keepdim=True), model.scales,
        model.opacities, sh, view[None], K[None], cam.width, cam.height, sh_degree=deg,
        eps2d=LOWPASS, backgrounds=background.to(dev, model.means.dtype)[None])
    radii = meta.get("radii")
    if radii is None:
        radii = torch.zeros(len(model), dtype=torch.int64)
    elif radii.dim() > 2:
        radii = radii.max(-1).values
    return RenderOutput(colors[0], alphas[0, ..., 0], radii.reshape(-1).to(torch.int64), 0)
