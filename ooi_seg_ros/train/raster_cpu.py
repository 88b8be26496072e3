"""Differentiable tile-based Gaussian rasteriser for the CPU.

Pipeline (as in 3DGS): EWA projection -> 3-sigma square -> list of (tile, Gaussian) pairs ->
one stable sort by depth then by tile -> per tile, front-to-back alpha compositing with early
termination -> background. Tiles are 16x16 pixels.

The compositing (the hot part) runs in a compiled C++ kernel (``raster_kernel``) when it can be
built; otherwise (no compiler, or ``kernel=False``) in the pure-torch path below, logged once.
Torch path: tiles are processed in batches of tiles with similar Gaussian counts, padded to the
batch maximum, so every step is one dense tensor operation; transmittance is a cumulative sum
of log(1 - alpha), whose backward is cheap. Large batches are wrapped in activation
checkpointing so memory stays bounded (``max_batch_elems``) at the price of recomputing them in
the backward pass. Both paths give the same image and gradients (tests), see BENCHMARKS.md for
their speed next to the brute-force reference.
"""

from __future__ import annotations

from typing import Optional

import torch
from torch.utils.checkpoint import checkpoint

from . import raster_kernel
from .gaussians import GaussianModel
from .raster_common import (ALPHA_MAX, ALPHA_MIN, Projected, RasterCamera, RenderOutput, T_MIN,
                            pixel_alpha, project)

TILE = 16


def _tile_pairs(pr: Projected, tiles_x: int, tiles_y: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(tile id, Gaussian id) pairs sorted by tile, then front to back (stable sorts)."""
    vis = torch.nonzero(pr.radii > 0).squeeze(1)
    if len(vis) == 0:
        e = torch.zeros(0, dtype=torch.int64)
        return e, e
    vis = vis[torch.argsort(pr.depths.detach()[vis], stable=True)]
    m = pr.means2d.detach()[vis]
    r = pr.radii[vis].to(m.dtype)
    # pixel centres sit at integer coordinates: tile i holds pixel columns [16 i, 16 i + 15]
    x0 = torch.floor((m[:, 0] - r + 0.5) / TILE).clamp(0, tiles_x).to(torch.int64)
    x1 = (torch.floor((m[:, 0] + r + 0.5) / TILE) + 1).clamp(0, tiles_x).to(torch.int64)
    y0 = torch.floor((m[:, 1] - r + 0.5) / TILE).clamp(0, tiles_y).to(torch.int64)
    y1 = (torch.floor((m[:, 1] + r + 0.5) / TILE) + 1).clamp(0, tiles_y).to(torch.int64)
    nx = (x1 - x0).clamp_min(0)
    ny = (y1 - y0).clamp_min(0)
    cnt = nx * ny
    gid = torch.repeat_interleave(torch.arange(len(vis)), cnt)
    start = torch.cumsum(cnt, 0) - cnt
    local = torch.arange(int(cnt.sum())) - torch.repeat_interleave(start, cnt)
    nxg = nx[gid]
    tx = x0[gid] + local % nxg.clamp_min(1)
    ty = y0[gid] + local // nxg.clamp_min(1)
    tile = ty * tiles_x + tx
    order = torch.argsort(tile, stable=True)  # keeps the depth order inside each tile
    return tile[order], vis[gid[order]]


def _composite(pix: torch.Tensor, m2: torch.Tensor, con: torch.Tensor, op: torch.Tensor,
               col: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Front-to-back compositing of a padded batch of tiles.

    pix [B, P, 2] pixel centres; m2 [B, K, 2]; con [B, K, 3]; op [B, K] (0 on padding);
    col [B, K, 3]. Returns colour [B, P, 3] (without background) and accumulated alpha [B, P].
    """
    dx = pix[:, None, :, 0] - m2[:, :, None, 0]
    dy = pix[:, None, :, 1] - m2[:, :, None, 1]
    alpha = pixel_alpha(dx, dy, con[:, :, None, :], op[:, :, None])  # [B, K, P]
    l1m = torch.log1p(-alpha)
    log_t = torch.cumsum(l1m, dim=1)
    t_excl = torch.exp(log_t - l1m)
    w = alpha * t_excl * (log_t.detach() >= torch.log(torch.tensor(T_MIN, dtype=alpha.dtype)))
    color = torch.einsum("bkp,bkc->bpc", w, col)
    return color, w.sum(1)


_LOG_TMIN = float(torch.log(torch.tensor(T_MIN)))


def _fwd_terms(pix, m2, con, op):
    """Recomputable forward pieces of the compositing (no autograd)."""
    dx = pix[:, None, :, 0] - m2[:, :, None, 0]
    dy = pix[:, None, :, 1] - m2[:, :, None, 1]
    power = (-0.5 * (con[..., 0, None] * dx * dx + con[..., 2, None] * dy * dy)
             - con[..., 1, None] * dx * dy)
    g = torch.exp(torch.clamp_max(power, 0.0))
    raw = op[..., None] * g
    alpha = torch.clamp_max(raw, ALPHA_MAX)
    keep = (power <= 0) & (alpha >= ALPHA_MIN)
    alpha = alpha * keep
    l1m = torch.log1p(-alpha)
    log_t = torch.cumsum(l1m, dim=1)
    t_excl = torch.exp(log_t - l1m) * (log_t >= _LOG_TMIN)
    return dx, dy, g, raw, keep, alpha, t_excl


class _CompositeFn(torch.autograd.Function):
    """Front-to-back compositing with a hand-written backward (recomputes the forward terms,
    so nothing of size tiles x K x 256 is kept between the passes)."""

    @staticmethod
    def forward(ctx, pix, m2, con, op, col):
        with torch.no_grad():
            _, _, _, _, _, alpha, t_excl = _fwd_terms(pix, m2, con, op)
            w = alpha * t_excl
            color = torch.einsum("bkp,bkc->bpc", w, col)
            acc = w.sum(1)
        ctx.save_for_backward(pix, m2, con, op, col)
        return color, acc

    @staticmethod
    def backward(ctx, g_color, g_acc):
        pix, m2, con, op, col = ctx.saved_tensors
        dx, dy, g, raw, keep, alpha, t_excl = _fwd_terms(pix, m2, con, op)
        w = alpha * t_excl
        if g_acc is None:
            g_acc = torch.zeros_like(pix[..., 0])
        if g_color is None:
            g_color = torch.zeros(pix.shape[0], pix.shape[1], 3, dtype=pix.dtype)
        # value of one unit of weight of Gaussian k at pixel p
        val = torch.einsum("bkc,bpc->bkp", col, g_color) + g_acc[:, None, :]
        wv = w * val
        behind = wv.sum(1, keepdim=True) - torch.cumsum(wv, dim=1)  # sum over j > k
        d_alpha = t_excl * val - behind / (1.0 - alpha)
        d_raw = d_alpha * keep * (raw < ALPHA_MAX)
        d_op = (d_raw * g).sum(-1)
        d_pow = d_raw * raw
        d_dx = -d_pow * (con[..., 0, None] * dx + con[..., 1, None] * dy)
        d_dy = -d_pow * (con[..., 2, None] * dy + con[..., 1, None] * dx)
        d_m2 = -torch.stack([d_dx.sum(-1), d_dy.sum(-1)], -1)
        d_con = torch.stack([(-0.5 * d_pow * dx * dx).sum(-1), (-d_pow * dx * dy).sum(-1),
                             (-0.5 * d_pow * dy * dy).sum(-1)], -1)
        d_col = torch.einsum("bkp,bpc->bkc", w, g_color)
        return None, d_m2, d_con, d_op, d_col


def render(model: GaussianModel, cam: RasterCamera, background: torch.Tensor,
           sh_degree: Optional[int] = None, max_batch_elems: int = 1 << 22,
           checkpoint_above: int = 1 << 25, fused: Optional[bool] = None,
           kernel: Optional[bool] = None) -> RenderOutput:
    """Render ``model`` from ``cam`` composited over ``background`` [3] (differentiable).

    ``kernel``: True/None use the compiled kernel (projection, SH colour and compositing) when
    it is available (None: silently fall back to torch; True: the same, the fallback is logged
    by the loader), False forces the pure-torch path, to which the remaining options apply.
    ``max_batch_elems`` bounds tiles x Gaussians x pixels of one dense batch. When the whole
    frame needs more than ``checkpoint_above`` such elements (or ``fused`` is True) the
    compositing uses the hand-written backward, which keeps no per-pixel intermediates (it
    recomputes them); below that, autograd's saved tensors make the backward a little faster.
    """
    deg = model.sh_degree if sh_degree is None else sh_degree
    use_kernel = kernel is not False and not fused and raster_kernel.available()
    proj = raster_kernel.project if use_kernel else project
    pr = proj(model.means, model.log_scales, model.quats, model.logit_opacities,
              model.sh_dc, model.sh_rest, cam, deg)
    return rasterize(pr, cam, background, max_batch_elems, checkpoint_above, fused, kernel)


def kernel_available() -> bool:
    """True when the compiled compositing kernel is usable (builds it on first call)."""
    return raster_kernel.available()


def rasterize(pr: Projected, cam: RasterCamera, background: torch.Tensor,
              max_batch_elems: int = 1 << 22, checkpoint_above: int = 1 << 25,
              fused: Optional[bool] = None, kernel: Optional[bool] = None) -> RenderOutput:
    """Tile rasterisation of already projected Gaussians (shared with other back-ends' tests)."""
    H, W = cam.height, cam.width
    tx, ty = (W + TILE - 1) // TILE, (H + TILE - 1) // TILE
    n_tiles = tx * ty
    dt = pr.means2d.dtype
    tile_of, gauss = _tile_pairs(pr, tx, ty)
    counts = torch.bincount(tile_of, minlength=n_tiles)
    if kernel is not False and not fused and raster_kernel.available():
        tile_start = torch.zeros(n_tiles + 1, dtype=torch.int64)
        torch.cumsum(counts, 0, out=tile_start[1:])
        col, acc = raster_kernel.composite(pr.means2d, pr.conics, pr.opacities,
                                           pr.colors.to(dt), gauss, tile_start, W, H, tx)
        img = col + (1.0 - acc)[..., None] * background.to(dt)
        return RenderOutput(img, acc, pr.radii, int(len(gauss)))
    starts = torch.cumsum(counts, 0) - counts
    # local pixel offsets inside a tile
    ly, lx = torch.meshgrid(torch.arange(TILE, dtype=dt), torch.arange(TILE, dtype=dt),
                            indexing="ij")
    loc = torch.stack([lx.reshape(-1), ly.reshape(-1)], -1)  # [256, 2]
    occupied = torch.nonzero(counts > 0).squeeze(1)
    occupied = occupied[torch.argsort(counts[occupied], stable=True)]
    total = int((counts[occupied].to(torch.float64) * TILE * TILE).sum()) if len(occupied) else 0
    use_ckpt = total > checkpoint_above and torch.is_grad_enabled()
    # padded gather tables need a dummy Gaussian at index N (zero opacity)
    m2_all = torch.cat([pr.means2d, pr.means2d.new_zeros(1, 2)])
    con_all = torch.cat([pr.conics, pr.conics.new_zeros(1, 3)])
    op_all = torch.cat([pr.opacities, pr.opacities.new_zeros(1)])
    col_all = torch.cat([pr.colors, pr.colors.new_zeros(1, 3)])
    dummy = pr.means2d.shape[0]
    colors, accs, ids = [], [], []
    i = 0
    n_occ = len(occupied)
    cnt_list = counts[occupied].tolist()
    while i < n_occ:
        # grow the batch while the padded size stays within budget (counts ascend)
        j = i + 1
        c0 = cnt_list[i]
        while j < n_occ:
            cj = int(cnt_list[j])
            # stop at the memory budget, or when padding would waste more than ~25%
            if (j + 1 - i) * cj * TILE * TILE > max_batch_elems or cj > 1.25 * c0 + 8:
                break
            j += 1
        tiles = occupied[i:j]
        k = int(counts[tiles].max())
        ar = torch.arange(k)
        idx = starts[tiles][:, None] + ar[None, :]
        valid = ar[None, :] < counts[tiles][:, None]
        g = torch.where(valid, gauss[idx.clamp_max(max(len(gauss) - 1, 0))],
                        torch.full_like(idx, dummy))
        origin = torch.stack([(tiles % tx) * TILE, (tiles // tx) * TILE], -1).to(dt)
        pix = origin[:, None, :] + loc[None, :, :]
        args = (pix, m2_all[g], con_all[g], op_all[g], col_all[g])
        if fused or (fused is None and use_ckpt):
            c, a = _CompositeFn.apply(*args)
        elif use_ckpt:
            c, a = checkpoint(_composite, *args, use_reentrant=False)
        else:
            c, a = _composite(*args)
        colors.append(c)
        accs.append(a)
        ids.append(tiles)
        i = j
    bg = background.to(dt)
    if ids:
        tid = torch.cat(ids)
        col_t = pr.means2d.new_zeros(n_tiles, TILE * TILE, 3).index_copy(0, tid, torch.cat(colors))
        acc_t = pr.means2d.new_zeros(n_tiles, TILE * TILE).index_copy(0, tid, torch.cat(accs))
    else:
        col_t = pr.means2d.new_zeros(n_tiles, TILE * TILE, 3)
        acc_t = pr.means2d.new_zeros(n_tiles, TILE * TILE)
    img = col_t + (1.0 - acc_t)[..., None] * bg
    img = img.reshape(ty, tx, TILE, TILE, 3).permute(0, 2, 1, 3, 4)
    img = img.reshape(ty * TILE, tx * TILE, 3)
    acc = acc_t.reshape(ty, tx, TILE, TILE).permute(0, 2, 1, 3).reshape(ty * TILE, tx * TILE)
    return RenderOutput(img[:H, :W], acc[:H, :W], pr.radii, int(len(gauss)))
