"""gsplat (CUDA) back-end with the same interface as ``raster_cpu.render``.

Optional: used only when the ``gsplat`` package imports and CUDA is available. gsplat puts
pixel centres at +0.5, this package at integer coordinates (ROS/OpenCV), hence cx/cy + 0.5.
The model may live on the CPU (the trainer keeps one code path for both back-ends): its
tensors are copied to the GPU for the rasterisation and the outputs come back to the model's
device, with gradients flowing through the copies. Checked against the CPU tile rasteriser
(image and gradients) on an H100 by ``test/test_raster_gsplat.py``; the tests skip cleanly
without CUDA.
"""

from __future__ import annotations

from typing import Optional

import torch

from .gaussians import GaussianModel
from .raster_common import RasterCamera, RenderOutput


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
    """Render with ``gsplat.rasterization`` on CUDA; outputs on the model's device."""
    from gsplat import rasterization

    deg = model.sh_degree if sh_degree is None else sh_degree
    home = model.means.device
    dev = home if home.type == "cuda" else torch.device("cuda")
    dt = torch.float32
    view = torch.eye(4, dtype=dt, device=dev)
    view[:3, :3] = cam.R.to(dev, dt)
    view[:3, 3] = cam.t.to(dev, dt)
    K = torch.tensor([[cam.fx, 0.0, cam.cx + 0.5], [0.0, cam.fy, cam.cy + 0.5], [0.0, 0.0, 1.0]],
                     dtype=dt, device=dev)
    quats = model.quats.to(dev, dt)
    sh = torch.cat([model.sh_dc[:, None, :], model.sh_rest], 1).to(dev, dt)
    n_coef = (deg + 1) ** 2
    colors, alphas, meta = rasterization(
        model.means.to(dev, dt), quats / quats.norm(dim=-1, keepdim=True),
        model.scales.to(dev, dt), model.opacities.to(dev, dt), sh[:, :n_coef], view[None],
        K[None], cam.width, cam.height, sh_degree=deg, eps2d=float(cam.lowpass),
        packed=False)
    # composite over the background here rather than with gsplat's ``backgrounds`` argument,
    # whose expected shape differs between its packed and unpacked modes (1.5.3)
    image = colors[0] + (1.0 - alphas[0]) * background.to(dev, dt)
    radii = meta.get("radii")
    if radii is None:
        radii = torch.zeros(len(model), dtype=torch.int64, device=dev)
    elif radii.dim() > 2:
        radii = radii.max(-1).values
    n_isect = meta.get("isect_ids")
    n_isect = int(n_isect.numel()) if torch.is_tensor(n_isect) else 0
    return RenderOutput(image.to(home), alphas[0, ..., 0].to(home),
                        radii.reshape(-1).to(torch.int64).to(home), n_isect)
