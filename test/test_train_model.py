"""Gaussian model PLY layout, masked loss/metrics, LPIPS path, MCMC relocation maths."""

import numpy as np
import torch

from ooi_seg_ros.train import mcmc
from ooi_seg_ros.train.gaussians import (PLY_FIELDS, init_from_points, load_ply, read_ply_header,
                                         save_ply)
from ooi_seg_ros.train.loss import (TinyLpips, load_lpips, masked_mean, masked_psnr,
                                    photometric_loss, ssim_map)

torch.set_num_threads(1)


def _model(n=50, seed=0):
    rng = np.random.default_rng(seed)
    m = init_from_points(rng.normal(size=(n, 3)), rng.integers(0, 255, (n, 3)))
    m.sh_rest = torch.randn(n, 15, 3, generator=torch.Generator().manual_seed(seed))
    m.quats = torch.randn(n, 4, generator=torch.Generator().manual_seed(seed + 1))
    return m


def test_ply_header_fields_and_roundtrip(tmp_path):
    m = _model()
    p = tmp_path / "s.ply"
    save_ply(m, p)
    head = p.read_bytes().split(b"end_header\n")[0].decode().splitlines()
    assert head[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 50"]
    props = [h.split()[2] for h in head[3:]]
    expected = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
                + [f"f_rest_{i}" for i in range(45)]
                + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert props == expected == PLY_FIELDS
    assert all(h.split()[1] == "float" for h in head[3:])
    names, count, off, fmt = read_ply_header(p)
    assert count == 50 and fmt == "binary_little_endian"
    assert p.stat().st_size == off + 50 * 62 * 4
    raw = np.frombuffer(p.read_bytes()[off:], "<f4").reshape(50, 62)
    # f_rest is channel-major (all red coefficients first), as the reference writes it
    assert np.allclose(raw[:, 9:24], m.sh_rest[:, :, 0].numpy())
    assert np.allclose(raw[:, 58:62], m.quats.numpy())  # rot_0 = w
    back = load_ply(p)
    for k, v in m.params().items():
        assert torch.allclose(getattr(back, k), v), k


def test_init_scales_from_neighbours():
    g = np.stack(np.meshgrid(np.arange(5), np.arange(5), np.arange(5)), -1).reshape(-1, 3) * 0.1
    m = init_from_points(g)
    assert np.allclose(m.scales.detach().numpy()[62], 0.1, atol=1e-5)  # interior point


def test_masked_loss_ignores_outside_pixels():
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(24, 32, 3, generator=g)
    mask = torch.zeros(24, 32, dtype=torch.bool)
    mask[6:18, 8:24] = True
    render = gt.clone()
    render[~mask] = torch.rand(int((~mask).sum()), 3, generator=g)
    assert float(photometric_loss(gt, gt, mask)) < 1e-6
    # outside pixels differ wildly, yet L1 inside is 0; only SSIM windows at the border see it
    assert float(photometric_loss(render, gt, mask)) < 0.05
    assert float(photometric_loss(render, gt, None)) > 0.1
    # mean over object pixels: a constant error inside gives that error, whatever the mask size
    off = gt + 0.1 * mask[..., None]
    l1_only = photometric_loss(off, gt, mask, lambda_dssim=0.0)
    assert abs(float(l1_only) - 0.1) < 1e-5
    assert masked_psnr(off, gt, mask) < 21 and masked_psnr(gt, gt, mask) == float("inf")
    assert abs(float(ssim_map(gt, gt).mean()) - 1.0) < 1e-5


def test_masked_loss_crop_is_exact():
    """The loss on the mask's padded bounding box equals the loss on the full image."""
    g = torch.Generator().manual_seed(1)
    gt = torch.rand(40, 50, 3, generator=g)
    for box in ((slice(10, 20), slice(12, 30)), (slice(0, 7), slice(40, 50)),
                (slice(3, 40), slice(0, 2))):
        mask = torch.zeros(40, 50, dtype=torch.bool)
        mask[box] = True
        mask[box[0].start, box[1].start] = False  # not a full rectangle
        r = torch.rand(40, 50, 3, generator=g).requires_grad_(True)
        full = (0.8 * masked_mean((r - gt).abs(), mask)
                + 0.2 * (1 - masked_mean(ssim_map(r, gt), mask)))
        crop = photometric_loss(r, gt, mask, 0.2)
        assert abs(float(full.detach()) - float(crop.detach())) < 1e-6
        ga, = torch.autograd.grad(full, r)
        gb, = torch.autograd.grad(crop, r)
        assert torch.allclose(ga, gb, atol=1e-7)


def test_lpips_random_weights_and_unavailable(tmp_path):
    assert load_lpips(None) is None
    assert load_lpips(tmp_path / "missing.pth") is None
    torch.manual_seed(0)
    net = TinyLpips()
    p = tmp_path / "w.pth"
    torch.save(net.state_dict(), p)
    net2 = load_lpips(p)
    a = torch.rand(32, 32, 3)
    with torch.no_grad():
        assert float(net2(a, a)) == 0.0
        assert float(net2(a, torch.rand(32, 32, 3), torch.ones(32, 32, dtype=torch.bool))) != 0.0


def test_relocation_update_preserves_opacity():
    o = torch.tensor([0.9, 0.5, 0.2, 0.7])
    s = torch.ones(4, 3)
    n = torch.tensor([1, 2, 3, 5])
    new_o, new_s = mcmc.relocation_update(o, s, n)
    assert torch.allclose(new_o[0], o[0]) and torch.allclose(new_s[0], s[0], atol=1e-5)
    # n stacked copies have the original's total opacity at the centre
    assert torch.allclose(1 - (1 - new_o) ** n.float(), o, atol=1e-5)
    assert (new_s[1:] < 1.5).all() and (new_s[1:] > 0).all()


def test_relocate_and_add():
    m = _model(20).requires_grad_(True)
    opt = torch.optim.Adam([{"params": [t]} for t in m.params().values()])
    with torch.no_grad():
        m.logit_opacities[:5] = -10.0  # dead
    m.means.sum().backward()
    opt.step()
    gen = torch.Generator().manual_seed(0)
    moved = mcmc.relocate(m, opt, mcmc.dead_mask(m), gen)
    assert moved == 5 and bool((m.opacities > 0.005).all())
    mcmc.add_new(m, opt, 7, gen)
    assert len(m) == 27 and all(len(t) == 27 for t in m.params().values())
    assert opt.param_groups[0]["params"][0] is m.means
    assert opt.state[m.means]["exp_avg"].shape == (27, 3)
    m.means.sum().backward()
    opt.step()  # the optimiser works on the grown tensors


def test_kernel_ssim_matches_torch():
    """The compiled masked SSIM gives the convolutional path's value and gradient."""
    from ooi_seg_ros.train import raster_kernel
    from ooi_seg_ros.train.loss import _gauss_window

    for dt in (torch.float64, torch.float32):
        g = torch.Generator().manual_seed(0)
        x = torch.rand(23, 31, 3, generator=g, dtype=dt, requires_grad=True)
        y = torch.rand(23, 31, 3, generator=g, dtype=dt)
        m = torch.rand(23, 31, generator=g) > 0.4
        ref = masked_mean(ssim_map(x, y), m)
        (gref,) = torch.autograd.grad(ref, x)
        val = raster_kernel.masked_ssim(x, y, m, _gauss_window(11, dtype=dt))
        (gk,) = torch.autograd.grad(val, x)
        tol = 1e-12 if dt == torch.float64 else 1e-6
        assert abs(float(val) - float(ref)) < tol
        assert float((gk - gref).abs().max()) < tol * float(gref.abs().max()) * 10
