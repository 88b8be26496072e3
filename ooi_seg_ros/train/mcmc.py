"""3DGS-MCMC densification (Kheradmand et al. 2024) with an object-mask constraint.

The Gaussians are samples of a distribution: a hard cap bounds their number, dead (near
transparent) Gaussians are relocated onto live ones drawn by opacity, with the opacity/scale
update that keeps the rendered image unchanged to first order, new Gaussians are added the same
way up to the cap, and positions get SGLD noise gated by (1 - opacity). Here Gaussians whose
centre projects outside the object mask in most views that see it are treated as dead too,
so none of the budget is spent on background.
"""

from __future__ import annotations

from math import comb
from typing import Optional

import torch

from .gaussians import GaussianModel
from .raster_common import RasterCamera, covariance_3d

MAX_COPIES = 51  # cap on copies of one Gaussian in one relocation (as in the reference)


def relocation_update(opacities: torch.Tensor, scales: torch.Tensor,
                      copies: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Opacity and scale for a Gaussian split into ``copies`` identical ones at one place.

    new_o = 1 - (1 - o)^(1/n); scale *= o / sum_{i=1..n} sum_{k<i} C(i-1,k) (-1)^k
    new_o^(k+1) / sqrt(k+1), so that n stacked copies render like the original.
    """
    n = copies.clamp(1, MAX_COPIES).to(torch.int64)
    new_o = 1.0 - torch.pow(1.0 - opacities, 1.0 / n.to(opacities.dtype))
    # coefficient table: coef[n, k] = sum over i=k+1..n of C(i-1, k) (-1)^k / sqrt(k+1)
    table = torch.zeros(MAX_COPIES + 1, MAX_COPIES, dtype=torch.float64)
    for i in range(1, MAX_COPIES + 1):
        for k in range(i):
            table[i, k] = comb(i - 1, k) * (-1) ** k / (k + 1) ** 0.5
    table = torch.cumsum(table, 0).to(opacities.dtype)
    powers = new_o[:, None] ** torch.arange(1, MAX_COPIES + 1, dtype=opacities.dtype)[None]
    denom = (table[n] * powers).sum(1)
    coef = opacities / denom.clamp_min(1e-12)
    return new_o.clamp(1e-4, 1 - 1e-4), scales * coef[:, None]


def _reset_adam(opt: torch.optim.Optimizer, idx: torch.Tensor) -> None:
    for group in opt.param_groups:
        for p in group["params"]:
            st = opt.state.get(p)
            if st:
                for key in ("exp_avg", "exp_avg_sq"):
                    if key in st:
                        st[key][idx] = 0


def _sample_sources(opac: torch.Tensor, live: torch.Tensor, n: int,
                    gen: torch.Generator) -> torch.Tensor:
    probs = opac * live
    if float(probs.sum()) <= 0:
        probs = torch.ones_like(opac)
    return torch.multinomial(probs, n, replacement=True, generator=gen)


@torch.no_grad()
def relocate(model: GaussianModel, opt: torch.optim.Optimizer, dead: torch.Tensor,
             gen: torch.Generator) -> int:
    """Move dead Gaussians onto live ones sampled by opacity; returns how many moved."""
    dead_idx = torch.nonzero(dead).squeeze(1)
    live = ~dead
    if len(dead_idx) == 0 or not bool(live.any()):
        return 0
    opac = model.opacities
    src = _sample_sources(opac, live.to(opac.dtype), len(dead_idx), gen)
    copies = torch.bincount(src, minlength=len(model))[src] + 1
    new_o, new_s = relocation_update(opac[src], model.scales[src], copies)
    logit = torch.log(new_o / (1 - new_o))
    for t in (model.logit_opacities,):
        t[src] = logit
    model.log_scales[src] = torch.log(new_s)
    for name, t in model.params().items():
        t[dead_idx] = t[src]
    _reset_adam(opt, torch.cat([dead_idx, src]))
    return int(len(dead_idx))


@torch.no_grad()
def add_new(model: GaussianModel, opt: torch.optim.Optimizer, n_add: int,
            gen: torch.Generator) -> int:
    """Append ``n_add`` Gaussians split off live ones (opacity-weighted); returns the count.

    Parameters are replaced by larger leaf tensors; the optimiser's params and Adam moments
    are swapped accordingly (new rows start with zero moments).
    """
    if n_add <= 0:
        return 0
    opac = model.opacities
    src = _sample_sources(opac, (opac > 0.005).to(opac.dtype), n_add, gen)
    copies = torch.bincount(src, minlength=len(model))[src] + 1
    new_o, new_s = relocation_update(opac[src], model.scales[src], copies)
    model.logit_opacities[src] = torch.log(new_o / (1 - new_o))
    model.log_scales[src] = torch.log(new_s)
    for name, old in model.params().items():
        new = torch.cat([old.detach(), old.detach()[src]]).requires_grad_(True)
        for group in opt.param_groups:
            if group["params"][0] is old:
                st = opt.state.pop(old, None)
                group["params"][0] = new
                if st:
                    for key in ("exp_avg", "exp_avg_sq"):
                        if key in st:
                            st[key] = torch.cat([st[key], torch.zeros_like(st[key][:n_add])])
                    opt.state[new] = st
        setattr(model, name, new)
    _reset_adam(opt, src)
    return n_add


@torch.no_grad()
def inject_noise(model: GaussianModel, lr_means: float, noise_lr: float = 5e5) -> None:
    """SGLD step: position noise shaped by each covariance, gated to low-opacity Gaussians."""
    opac = model.opacities
    gate = torch.sigmoid(100.0 * ((1.0 - opac) - 0.995))
    cov = covariance_3d(model.log_scales, model.quats)
    noise = torch.randn_like(model.means)
    noise = (cov @ noise[:, :, None]).squeeze(-1) * (gate * noise_lr * lr_means)[:, None]
    model.means.add_(noise)


@torch.no_grad()
def outside_mask_fraction(means: torch.Tensor, cams: list[RasterCamera],
                          masks: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """(fraction of the views that see a centre where it falls outside the mask, views seeing it).

    A view "sees" a centre when it projects inside the image in front of the camera.
    """
    outside = torch.zeros(len(means), dtype=torch.float32)
    seen = torch.zeros(len(means), dtype=torch.float32)
    for cam, mask in zip(cams, masks):
        pc = means @ cam.R.T.to(means.dtype) + cam.t.to(means.dtype)
        z = pc[:, 2]
        u = torch.round(cam.fx * pc[:, 0] / z.clamp_min(1e-6) + cam.cx).to(torch.int64)
        v = torch.round(cam.fy * pc[:, 1] / z.clamp_min(1e-6) + cam.cy).to(torch.int64)
        ok = (z > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        inside = torch.zeros_like(ok)
        inside[ok] = mask[v[ok], u[ok]].bool()
        seen += ok.float()
        outside += (ok & ~inside).float()
    return outside / seen.clamp_min(1.0), seen


def regularisation(model: GaussianModel, opacity_reg: float, scale_reg: float) -> torch.Tensor:
    """MCMC's L1 penalties on opacity and scale (push unused Gaussians to die)."""
    return (opacity_reg * model.opacities.abs().mean()
            + scale_reg * model.scales.abs().mean())


def dead_mask(model: GaussianModel, min_opacity: float = 0.005,
              outside_frac: Optional[torch.Tensor] = None,
              outside_limit: float = 0.5) -> torch.Tensor:
    """Dead = near transparent, or (with ``outside_frac``) mostly outside the object masks."""
    dead = model.opacities.detach() <= min_opacity
    if outside_frac is not None:
        dead = dead | (outside_frac > outside_limit)
    return dead
