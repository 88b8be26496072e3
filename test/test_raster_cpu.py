"""Tile rasteriser (compiled kernel and pure-torch paths) vs brute-force reference, gradients,
and the gsplat back-end (CUDA only)."""

import functools

import numpy as np
import pytest
import torch

from ooi_seg_ros.core.geometry import look_at
from ooi_seg_ros.core.types import CameraIntrinsics
from ooi_seg_ros.train import raster_cpu, raster_kernel, raster_reference
from ooi_seg_ros.train.gaussians import init_from_points
from ooi_seg_ros.train.raster_common import RasterCamera

torch.set_num_threads(1)

# both compositing paths: the compiled kernel (must build here: g++ is a test prerequisite)
# and the pure-torch fallback
PATHS = pytest.mark.parametrize("kernel", [True, False], ids=["kernel", "torch"])


def _render(kernel):
    return functools.partial(raster_cpu.render, kernel=kernel)


def test_kernel_builds():
    assert raster_kernel.available(), raster_kernel.unavailable_reason()


def _scene(n=200, w=48, h=36, seed=0, dtype=torch.float32):
    rng = np.random.default_rng(seed)
    m = init_from_points(rng.normal(size=(n, 3)) * 0.5, rng.integers(0, 255, (n, 3)),
                         initial_opacity=0.6)
    m.sh_degree = 2
    g = torch.Generator().manual_seed(seed)
    m.sh_rest[:, :8] = torch.randn(n, 8, 3, generator=g) * 0.2
    m.quats = torch.randn(n, 4, generator=g)
    m.log_scales = m.log_scales + torch.randn(n, 3, generator=g) * 0.3
    for k, v in m.params().items():
        setattr(m, k, v.to(dtype))
    cam = CameraIntrinsics(width=w, height=h, fx=0.9 * w, fy=0.9 * w, cx=(w - 1) / 2,
                           cy=(h - 1) / 2)
    rc = RasterCamera.from_view(cam, look_at(np.array([3.0, 1.0, 1.2]), np.zeros(3)), dtype)
    return m, rc


@PATHS
def test_tile_matches_reference(kernel):
    m, rc = _scene()
    bg = torch.tensor([0.1, 0.5, 0.9])
    a = _render(kernel)(m, rc, bg)
    b = raster_reference.render(m, rc, bg)
    assert a.image.shape == (36, 48, 3)
    assert a.n_intersections > b.n_intersections > 100  # tiles are shared by Gaussians
    assert float((a.image - b.image).abs().max()) < 2e-2
    assert float((a.image - b.image).abs().mean()) < 1e-3
    assert float((a.alpha - b.alpha).abs().max()) < 2e-2


@PATHS
def test_background_and_empty_scene(kernel):
    m, rc = _scene(n=5)
    with torch.no_grad():
        m.means += 100.0  # all behind / outside
    bg = torch.tensor([0.2, 0.4, 0.6])
    out = _render(kernel)(m, rc, bg)
    assert torch.allclose(out.image, bg.expand(36, 48, 3))
    assert int((out.radii > 0).sum()) == 0


def test_small_batches_same_image():
    m, rc = _scene()
    bg = torch.zeros(3)
    a = raster_cpu.render(m, rc, bg, kernel=False)
    b = raster_cpu.render(m, rc, bg, max_batch_elems=2000, checkpoint_above=0, kernel=False)
    assert torch.allclose(a.image, b.image, atol=1e-6)
    c = raster_cpu.render(m, rc, bg, kernel=True)
    assert torch.allclose(a.image, c.image, atol=1e-5)
    assert torch.allclose(a.alpha, c.alpha, atol=1e-5)


def test_kernel_odd_size_and_opaque_stack():
    """Partial edge tiles, and opaque Gaussians stacked so pixels terminate early."""
    m, rc = _scene(n=300, w=37, h=21, seed=5)
    with torch.no_grad():
        m.logit_opacities.fill_(6.0)  # alpha clamps at 0.99: early termination everywhere
    bg = torch.tensor([0.5, 0.2, 0.1])
    a = raster_cpu.render(m, rc, bg, kernel=True)
    b = raster_cpu.render(m, rc, bg, kernel=False)
    assert a.image.shape == (21, 37, 3)
    assert float((a.image - b.image).abs().max()) < 1e-4
    assert float((a.alpha - b.alpha).abs().max()) < 1e-4


def test_gradients_match_reference():
    m, rc = _scene(n=60, w=32, h=24)
    bg = torch.tensor([0.3, 0.3, 0.3])
    grads = []
    fused = functools.partial(raster_cpu.render, fused=True, kernel=False)
    for r in (_render(False), raster_reference.render, fused, _render(True)):
        mm = m.detached().requires_grad_(True)
        mm.sh_degree = 2
        w = torch.linspace(0, 1, 32 * 24 * 3).reshape(24, 32, 3)
        (r(mm, rc, bg).image * w).sum().backward()
        grads.append({k: v.grad.clone() for k, v in mm.params().items()})
    for k in ("means", "sh_dc", "logit_opacities", "log_scales"):
        a, b, c, d = grads[0][k], grads[1][k], grads[2][k], grads[3][k]
        assert float((a - b).norm() / b.norm().clamp_min(1e-9)) < 0.05, k
        assert float((a - c).norm() / a.norm().clamp_min(1e-9)) < 1e-4, k
        assert float((a - d).norm() / a.norm().clamp_min(1e-9)) < 1e-4, k


def test_gradcheck_float64():
    m, rc = _scene(n=6, w=16, h=12, seed=3, dtype=torch.float64)
    bg = torch.tensor([0.2, 0.1, 0.4], dtype=torch.float64)
    m.sh_degree = 1

    for fused, kernel in ((False, False), (True, False), (False, True)):
        def f(means, dc, logit_o, log_s):
            mm = m.detached()
            mm.means, mm.sh_dc, mm.logit_opacities, mm.log_scales = means, dc, logit_o, log_s
            mm.sh_degree = 1
            out = raster_cpu.render(mm, rc, bg, fused=fused, kernel=kernel)
            return out.image, out.alpha

        inputs = tuple(t.detach().clone().requires_grad_(True)
                       for t in (m.means, m.sh_dc, m.logit_opacities, m.log_scales))
        assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-4, rtol=1e-3)


@pytest.fixture
def fresh_kernel_loader(monkeypatch):
    """Forget the loaded kernel for one test (restored afterwards)."""
    saved = (raster_kernel._lib, raster_kernel._tried, raster_kernel._why_not)
    monkeypatch.setattr(raster_kernel, "_lib", None)
    monkeypatch.setattr(raster_kernel, "_tried", False)
    monkeypatch.setattr(raster_kernel, "_why_not", "")
    yield
    raster_kernel._lib, raster_kernel._tried, raster_kernel._why_not = saved


def test_fallback_without_compiler_is_logged(fresh_kernel_loader, monkeypatch, tmp_path,
                                             caplog):
    """No usable C++ compiler: one warning saying why, and rendering runs on the torch path."""
    monkeypatch.setenv("OOI_SEG_KERNEL_DIR", str(tmp_path))
    monkeypatch.setenv("CXX", str(tmp_path / "no-such-compiler"))
    m, rc = _scene(n=50)
    bg = torch.zeros(3)
    with caplog.at_level("WARNING", logger=raster_kernel.__name__):
        out = raster_cpu.render(m, rc, bg)
        raster_cpu.render(m, rc, bg)  # logged once, not per call
    warnings = [r for r in caplog.records if "pure-torch" in r.getMessage()]
    assert len(warnings) == 1 and "no-such-compiler" in warnings[0].getMessage()
    assert not raster_kernel.available() and raster_kernel.unavailable_reason()
    ref = raster_cpu.render(m, rc, bg, kernel=False)
    assert torch.allclose(out.image, ref.image)


@pytest.mark.slow
def test_kernel_builds_into_empty_cache(fresh_kernel_loader, monkeypatch, tmp_path):
    """A fresh machine (empty cache) compiles the kernel with the system compiler."""
    monkeypatch.setenv("OOI_SEG_KERNEL_DIR", str(tmp_path))
    assert raster_kernel.available(), raster_kernel.unavailable_reason()
    assert len(list(tmp_path.glob("ooi_composite_*.so"))) == 1
    m, rc = _scene(n=50)
    a = raster_cpu.render(m, rc, torch.zeros(3), kernel=True)
    b = raster_cpu.render(m, rc, torch.zeros(3), kernel=False)
    assert torch.allclose(a.image, b.image, atol=1e-5)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_kernel_projection_matches_torch(degree):
    """The compiled EWA projection + SH colour gives the torch path's values and gradients,
    also for Gaussians behind the camera and far outside the frustum (clamped Jacobian)."""
    from ooi_seg_ros.train import raster_common

    m, rc = _scene(n=300, seed=2, dtype=torch.float64)
    with torch.no_grad():
        m.sh_rest.normal_(0.0, 0.3, generator=torch.Generator().manual_seed(4))
        m.means.mul_(4.0)  # some behind the camera, many outside the image
    pc = m.means @ rc.R.T + rc.t
    assert int((pc[:, 2] < 0).sum()) > 5
    res = []
    for proj in (raster_common.project, raster_kernel.project):
        mm = m.detached().requires_grad_(True)
        pr = proj(mm.means, mm.log_scales, mm.quats, mm.logit_opacities, mm.sh_dc, mm.sh_rest,
                  rc, degree)
        g = torch.Generator().manual_seed(1)
        loss = sum((t * torch.randn(t.shape, generator=g, dtype=t.dtype)).sum()
                   for t in (pr.means2d, pr.conics, pr.colors, pr.opacities))
        loss.backward()
        grads = {k: (v.grad if v.grad is not None else torch.zeros_like(v))
                 for k, v in mm.params().items()}
        res.append((pr, grads))
    (a, ga), (b, gb) = res
    assert torch.equal(a.radii, b.radii)
    for x, y in ((a.means2d, b.means2d), (a.conics, b.conics), (a.colors, b.colors),
                 (a.depths, b.depths)):
        assert torch.allclose(x.detach(), y.detach(), rtol=1e-10, atol=1e-12)
    for k in ga:
        assert torch.allclose(ga[k], gb[k], rtol=1e-9, atol=1e-12), k


def test_kernel_projection_gradcheck():
    """Finite differences through the compiled projection: every parameter, SH degree 3."""
    m, rc = _scene(n=5, w=16, h=12, seed=3, dtype=torch.float64)
    with torch.no_grad():
        m.sh_rest.normal_(0.0, 0.3, generator=torch.Generator().manual_seed(5))

    def f(means, log_s, quats, dc, rest):
        pr = raster_kernel.project(means, log_s, quats, m.logit_opacities, dc, rest, rc, 3)
        return pr.means2d, pr.conics, pr.colors

    inputs = tuple(t.detach().clone().requires_grad_(True)
                   for t in (m.means, m.log_scales, m.quats, m.sh_dc, m.sh_rest))
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_camera_lowpass_reaches_every_path():
    """A camera's own ``lowpass`` (the 2D dilation, 3DGS: 0.3 px^2) is used by the kernel and
    torch projections and by the reference: same image and gradients at 0.05, and small
    Gaussians cover less of the image (smaller footprints) than at 0.3."""
    import dataclasses

    m, rc = _scene(n=80, w=32, h=24, seed=7, dtype=torch.float64)
    with torch.no_grad():
        m.log_scales -= 2.5  # sub-pixel Gaussians: the dilation dominates their footprint
    sharp = dataclasses.replace(rc, lowpass=0.05)
    bg = torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64)
    w = torch.linspace(0, 1, 24 * 32 * 3, dtype=torch.float64).reshape(24, 32, 3)
    out, grads = [], []
    for r in (_render(True), _render(False), raster_reference.render):
        mm = m.detached().requires_grad_(True)
        mm.sh_degree = 2
        o = r(mm, sharp, bg)
        (o.image * w).sum().backward()
        out.append(o)
        grads.append({k: v.grad.clone() for k, v in mm.params().items()})
    assert float((out[0].image - out[1].image).detach().abs().max()) < 1e-9
    assert float((out[0].image - out[2].image).detach().abs().mean()) < 1e-3
    for k in ("means", "log_scales", "logit_opacities", "sh_dc"):
        a, b, c = grads[0][k], grads[1][k], grads[2][k]
        assert float((a - b).norm() / b.norm().clamp_min(1e-12)) < 1e-6, k
        assert float((a - c).norm() / c.norm().clamp_min(1e-12)) < 0.05, k
    soft = _render(True)(m, rc, bg)
    assert float(out[0].alpha.detach().sum()) < 0.6 * float(soft.alpha.detach().sum())
    assert dataclasses.replace(rc).lowpass == rc.to(torch.float32).lowpass == 0.3
