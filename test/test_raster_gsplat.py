"""The gsplat (CUDA) back-end against the CPU tile rasteriser: image, alpha and gradients.

These run only where CUDA and the optional ``gsplat`` package are present (they skip cleanly
elsewhere, e.g. in CI); ``test_backend_choice_without_gsplat`` runs everywhere.
"""

import numpy as np
import pytest
import torch

from ooi_seg_ros.core.geometry import look_at
from ooi_seg_ros.core.types import CameraIntrinsics
from ooi_seg_ros.train import raster_cpu
from ooi_seg_ros.train.gaussians import init_from_points
from ooi_seg_ros.train.raster_common import RasterCamera

needs_gsplat = pytest.mark.skipif(not torch.cuda.is_available(), reason="gsplat needs CUDA")


def _scene(n=300, w=64, h=48, seed=0, degree=2):
    rng = np.random.default_rng(seed)
    m = init_from_points(rng.normal(size=(n, 3)) * 0.5, rng.integers(0, 255, (n, 3)),
                         initial_opacity=0.6)
    m.sh_degree = degree
    g = torch.Generator().manual_seed(seed)
    m.sh_rest[:, :8] = torch.randn(n, 8, 3, generator=g) * 0.2
    m.quats = torch.randn(n, 4, generator=g)
    m.log_scales = m.log_scales + torch.randn(n, 3, generator=g) * 0.3
    cam = CameraIntrinsics(width=w, height=h, fx=0.9 * w, fy=0.9 * w, cx=(w - 1) / 2 + 1.5,
                           cy=(h - 1) / 2 - 2.0)
    rc = RasterCamera.from_view(cam, look_at(np.array([3.0, 1.0, 1.2]), np.zeros(3)))
    return m, rc


@pytest.mark.gpu
@needs_gsplat
@pytest.mark.parametrize("degree", [0, 1, 3])
def test_gsplat_image_matches_cpu(degree):
    pytest.importorskip("gsplat")
    from ooi_seg_ros.train import raster_gsplat
    m, rc = _scene(degree=degree)
    bg = torch.tensor([0.1, 0.5, 0.9])
    a = raster_cpu.render(m, rc, bg)
    for model in (m, m.to("cuda")):  # CPU-resident model (trainer) and CUDA-resident model
        b = raster_gsplat.render(model, rc, bg)
        assert b.image.device == model.means.device
        img, alpha = b.image.cpu(), b.alpha.cpu()
        assert float((a.image - img).abs().mean()) < 5e-3
        assert float((a.image - img).abs().max()) < 0.1
        assert float((a.alpha - alpha).abs().mean()) < 5e-3
        # the same Gaussians are drawn (radii within a pixel: 3-sigma vs gsplat's rounding)
        drawn_a, drawn_b = a.radii > 0, b.radii.cpu() > 0
        assert float((drawn_a == drawn_b).float().mean()) > 0.98


@pytest.mark.gpu
@needs_gsplat
def test_gsplat_honours_the_cameras_lowpass():
    """Sub-pixel Gaussians, where the 2D low-pass filter sets the footprint: both back-ends
    agree at each setting, and the setting changes the image (gsplat gets ``eps2d``)."""
    pytest.importorskip("gsplat")
    import dataclasses

    from ooi_seg_ros.train import raster_gsplat
    m, rc = _scene(degree=0)
    m.log_scales = m.log_scales * 0 + float(np.log(0.002))
    bg = torch.tensor([0.2, 0.2, 0.2])
    imgs = {}
    for lp in (0.03, 1.0):
        c = dataclasses.replace(rc, lowpass=lp)
        a, b = raster_cpu.render(m, c, bg), raster_gsplat.render(m, c, bg)
        assert float((a.image - b.image.cpu()).abs().mean()) < 5e-3, lp
        assert float((a.alpha - b.alpha.cpu()).abs().mean()) < 5e-3, lp
        imgs[lp] = b.image.cpu()
    assert float((imgs[0.03] - imgs[1.0]).abs().mean()) > 5e-3


@pytest.mark.gpu
@needs_gsplat
def test_gsplat_gradients_match_cpu():
    pytest.importorskip("gsplat")
    from ooi_seg_ros.train import raster_gsplat
    m, rc = _scene(n=120, w=48, h=36, degree=1)
    bg = torch.tensor([0.3, 0.3, 0.3])
    wgt = torch.linspace(0, 1, 48 * 36 * 3).reshape(36, 48, 3)
    grads = []
    for r in (raster_cpu.render, raster_gsplat.render):
        mm = m.detached().requires_grad_(True)
        mm.sh_degree = 1
        (r(mm, rc, bg).image * wgt).sum().backward()
        grads.append({k: v.grad.clone() for k, v in mm.params().items()})
    for k in ("means", "sh_dc", "logit_opacities", "log_scales", "quats"):
        a, b = grads[0][k], grads[1][k]
        rel = float((a - b).norm() / a.norm().clamp_min(1e-9))
        assert rel < 0.1, (k, rel)


def test_backend_choice_without_gsplat():
    from ooi_seg_ros.train.raster_gsplat import gsplat_available
    from ooi_seg_ros.train.trainer import choose_backend
    if gsplat_available():
        assert choose_backend("auto") == "gsplat"
    else:
        assert choose_backend("auto") == "cpu"
        with pytest.raises(Exception, match="gsplat"):
            choose_backend("gsplat")
