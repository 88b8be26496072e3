"""Compiled CPU kernel for the per-tile alpha compositing (forward and backward).

The hot part of the CPU rasteriser is front-to-back compositing of every (tile, Gaussian) pair
over the tile's 256 pixels. In torch that is a dense [tiles, K, 256] computation per tensor op;
here it is one C++ loop per tile which
- evaluates a Gaussian only on the chord of each tile row where its alpha can reach 1/255
  (the exact ellipse ``d^T conic d <= 2 log(255 o)``, so the result is the same as evaluating
  every pixel and thresholding),
- stops a pixel once its transmittance would fall below T_MIN and a tile once all its pixels
  stopped,
- keeps only the final transmittance and the number of contributors per pixel for the
  backward pass, which walks each tile back to front (as the reference 3DGS does).
The backward adds each (tile, Gaussian) pair's gradient into its Gaussian's row in one thread,
in a fixed order, so the result is deterministic.

The EWA projection and the spherical-harmonics colour (``project``) run here too, forward and
backward by hand: under autograd they cost as much as the compositing (measured ~40 ms of a
~120 ms step at 16k Gaussians and SH degree 3), most of it in small tensor operations.

The library is plain C++ (no torch headers), compiled once with the system C++ compiler into a
cache directory (``$OOI_SEG_KERNEL_DIR`` or ``~/.cache/ooi_seg_ros/kernels``, keyed by a hash
of the source, flags and CPU) and called through ctypes. When no compiler is available or the
build fails, ``load()`` logs why once and returns None; the rasteriser then uses its pure-torch
path. ``OOI_SEG_NO_KERNEL=1`` forces the torch path.

    python -m ooi_seg_ros.train.raster_kernel   # build now (prints the library path)
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Optional

import torch

from .raster_common import (ALPHA_MAX, ALPHA_MIN, NEAR, Projected, RasterCamera,
                            T_MIN)

log = logging.getLogger(__name__)

TILE = 16
N_PAIR_GRADS = 9  # per Gaussian: d mean2d (2), d conic (3), d opacity (1), d colour (3)

_SOURCE = r"""
#include <algorithm>
#include <cmath>
#include <cstdint>

namespace {

constexpr int TILE = 16;
constexpr int NPIX = TILE * TILE;

// Per-Gaussian quantities for one tile: chord of each tile row where alpha >= ALPHA_MIN.
template <typename T>
struct Splat {
  T mx, my, a, b, c, o, qmax;
  bool ok;
};

template <typename T>
inline Splat<T> make_splat(const T* m2, const T* con, const T* op, int64_t g, T alpha_min) {
  Splat<T> s;
  s.mx = m2[2 * g];
  s.my = m2[2 * g + 1];
  s.a = con[3 * g];
  s.b = con[3 * g + 1];
  s.c = con[3 * g + 2];
  s.o = op[g];
  // alpha = o exp(-q/2) >= alpha_min  <=>  q <= 2 log(o / alpha_min)
  s.ok = s.o >= alpha_min;
  s.qmax = s.ok ? T(2) * std::log(s.o / alpha_min) : T(0);
  return s;
}

// Pixel columns [xs, xe] of row y (inside [x0, x1)) whose quadratic form is <= qmax.
// Returns false when the row misses the ellipse. Falls back to the full row when the conic is
// not positive definite (then the per-pixel test decides).
template <typename T>
inline bool row_span(const Splat<T>& s, int y, int x0, int x1, int& xs, int& xe) {
  T dy = T(y) - s.my;
  if (!(s.a > T(0))) {
    xs = x0;
    xe = x1 - 1;
    return true;
  }
  T bdy = s.b * dy;
  T disc = bdy * bdy - s.a * (s.c * dy * dy - s.qmax);
  if (!(disc >= T(0))) return false;
  T sq = std::sqrt(disc);
  // a small margin: the exact per-pixel test below decides at the boundary
  T lo = s.mx + (-bdy - sq) / s.a - T(1e-3);
  T hi = s.mx + (-bdy + sq) / s.a + T(1e-3);
  if (!(hi >= T(x0)) || !(lo <= T(x1 - 1))) return false;
  // clamp before the integer conversion (a huge footprint must not overflow int)
  xs = (int)std::ceil(std::max(lo, T(x0)));
  xe = (int)std::floor(std::min(hi, T(x1 - 1)));
  return xs <= xe;
}

// alpha of splat s at pixel offset (dx, dy); returns false when skipped (as the torch path:
// power > 0 or alpha < alpha_min). g = exp(power), raw = o * g before the clamp.
template <typename T>
inline bool pixel_alpha(const Splat<T>& s, T dx, T dy, T alpha_max, T alpha_min, T& g, T& raw,
                        T& alpha) {
  T power = T(-0.5) * (s.a * dx * dx + s.c * dy * dy) - s.b * dx * dy;
  if (power > T(0)) return false;
  g = std::exp(power);
  raw = s.o * g;
  alpha = std::min(alpha_max, raw);
  return alpha >= alpha_min;
}

template <typename T>
void forward(int W, int H, int tiles_x, int64_t n_tiles, const int64_t* tile_start,
             const int64_t* gid, const T* m2, const T* con, const T* op, const T* col,
             T alpha_max, T alpha_min, T t_min, T* out_col, T* out_t, int32_t* out_n) {
  for (int64_t tile = 0; tile < n_tiles; ++tile) {
    const int x0 = int(tile % tiles_x) * TILE, y0 = int(tile / tiles_x) * TILE;
    const int x1 = std::min(x0 + TILE, W), y1 = std::min(y0 + TILE, H);
    T tr[NPIX], cr[NPIX * 3];
    int32_t last[NPIX];
    bool done[NPIX];
    int n_live = (x1 - x0) * (y1 - y0);
    for (int p = 0; p < NPIX; ++p) {
      tr[p] = T(1);
      cr[3 * p] = cr[3 * p + 1] = cr[3 * p + 2] = T(0);
      last[p] = 0;
      done[p] = false;
    }
    const int64_t s0 = tile_start[tile], s1 = tile_start[tile + 1];
    for (int64_t k = s0; k < s1 && n_live > 0; ++k) {
      const int64_t g = gid[k];
      Splat<T> s = make_splat(m2, con, op, g, alpha_min);
      if (!s.ok) continue;
      const T c0 = col[3 * g], c1 = col[3 * g + 1], c2 = col[3 * g + 2];
      for (int y = y0; y < y1; ++y) {
        int xs, xe;
        if (!row_span(s, y, x0, x1, xs, xe)) continue;
        const T dy = T(y) - s.my;
        for (int x = xs; x <= xe; ++x) {
          const int p = (y - y0) * TILE + (x - x0);
          if (done[p]) continue;
          T gg, raw, alpha;
          if (!pixel_alpha(s, T(x) - s.mx, dy, alpha_max, alpha_min, gg, raw, alpha)) continue;
          const T tn = tr[p] * (T(1) - alpha);
          if (tn < t_min) {
            done[p] = true;
            --n_live;
            continue;
          }
          const T w = alpha * tr[p];
          cr[3 * p] += w * c0;
          cr[3 * p + 1] += w * c1;
          cr[3 * p + 2] += w * c2;
          tr[p] = tn;
          last[p] = int32_t(k - s0 + 1);
        }
      }
    }
    for (int y = y0; y < y1; ++y)
      for (int x = x0; x < x1; ++x) {
        const int p = (y - y0) * TILE + (x - x0);
        const int64_t q = int64_t(y) * W + x;
        out_col[3 * q] = cr[3 * p];
        out_col[3 * q + 1] = cr[3 * p + 1];
        out_col[3 * q + 2] = cr[3 * p + 2];
        out_t[q] = tr[p];
        out_n[q] = last[p];
      }
  }
}

template <typename T>
void backward(int W, int H, int tiles_x, int64_t n_tiles, const int64_t* tile_start,
              const int64_t* gid, const T* m2, const T* con, const T* op, const T* col,
              T alpha_max, T alpha_min, const T* fin_t, const int32_t* n_contrib,
              const T* g_col, const T* g_acc, T* grad) {
  for (int64_t tile = 0; tile < n_tiles; ++tile) {
    const int x0 = int(tile % tiles_x) * TILE, y0 = int(tile / tiles_x) * TILE;
    const int x1 = std::min(x0 + TILE, W), y1 = std::min(y0 + TILE, H);
    const int64_t s0 = tile_start[tile], s1 = tile_start[tile + 1];
    if (s1 == s0) continue;
    T tr[NPIX], behind[NPIX], gc[NPIX * 3], ga[NPIX];
    int32_t last[NPIX];
    int32_t max_last = 0;
    bool any_grad = false;
    for (int p = 0; p < NPIX; ++p) {
      tr[p] = T(1);
      behind[p] = T(0);
      gc[3 * p] = gc[3 * p + 1] = gc[3 * p + 2] = ga[p] = T(0);
      last[p] = 0;
    }
    for (int y = y0; y < y1; ++y)
      for (int x = x0; x < x1; ++x) {
        const int p = (y - y0) * TILE + (x - x0);
        const int64_t q = int64_t(y) * W + x;
        tr[p] = fin_t[q];
        last[p] = n_contrib[q];
        max_last = std::max(max_last, last[p]);
        gc[3 * p] = g_col[3 * q];
        gc[3 * p + 1] = g_col[3 * q + 1];
        gc[3 * p + 2] = g_col[3 * q + 2];
        ga[p] = g_acc[q];
        any_grad = any_grad || gc[3 * p] != T(0) || gc[3 * p + 1] != T(0) ||
                   gc[3 * p + 2] != T(0) || ga[p] != T(0);
      }
    // e.g. tiles outside an object mask: every pair gradient would be zero
    if (!any_grad) continue;
    for (int64_t k = s0 + max_last - 1; k >= s0; --k) {
      const int32_t li = int32_t(k - s0);
      const int64_t g = gid[k];
      T* pg = grad + g * 9;  // one thread: a fixed summation order
      Splat<T> s = make_splat(m2, con, op, g, alpha_min);
      if (!s.ok) continue;
      const T c0 = col[3 * g], c1 = col[3 * g + 1], c2 = col[3 * g + 2];
      T gmx = 0, gmy = 0, ga_ = 0, gb = 0, gc_ = 0, go = 0, gr = 0, gg_ = 0, gbl = 0;
      for (int y = y0; y < y1; ++y) {
        int xs, xe;
        if (!row_span(s, y, x0, x1, xs, xe)) continue;
        const T dy = T(y) - s.my;
        for (int x = xs; x <= xe; ++x) {
          const int p = (y - y0) * TILE + (x - x0);
          if (li >= last[p]) continue;
          const T dx = T(x) - s.mx;
          T gex, raw, alpha;
          if (!pixel_alpha(s, dx, dy, alpha_max, alpha_min, gex, raw, alpha)) continue;
          const T one_m = T(1) - alpha;
          const T tb = tr[p] / one_m;
          const T val = c0 * gc[3 * p] + c1 * gc[3 * p + 1] + c2 * gc[3 * p + 2] + ga[p];
          const T w = alpha * tb;
          const T d_alpha = tb * val - behind[p] / one_m;
          behind[p] += w * val;
          tr[p] = tb;
          gr += w * gc[3 * p];
          gg_ += w * gc[3 * p + 1];
          gbl += w * gc[3 * p + 2];
          if (raw < alpha_max) {
            go += d_alpha * gex;
            const T d_pow = d_alpha * raw;
            gmx += d_pow * (s.a * dx + s.b * dy);
            gmy += d_pow * (s.c * dy + s.b * dx);
            ga_ += T(-0.5) * d_pow * dx * dx;
            gb += -d_pow * dx * dy;
            gc_ += T(-0.5) * d_pow * dy * dy;
          }
        }
      }
      pg[0] += gmx;
      pg[1] += gmy;
      pg[2] += ga_;
      pg[3] += gb;
      pg[4] += gc_;
      pg[5] += go;
      pg[6] += gr;
      pg[7] += gg_;
      pg[8] += gbl;
    }
  }
}


// ---------------------------------------------------------------- projection (EWA) + SH colour

constexpr double SH_C0 = 0.28209479177387814;
constexpr double SH_C1 = 0.4886025119029199;
constexpr double SH_C2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                             -1.0925484305920792, 0.5462742152960396};
constexpr double SH_C3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
                             0.3731763325901154, -0.4570457994644658, 1.445305721320277,
                             -0.5900435899266435};

// Real SH basis (the reference 3DGS order, without the DC term) at unit direction (x, y, z),
// and optionally its partial derivatives d[k][0..2].
template <typename T>
inline void sh_basis(int deg, T x, T y, T z, T* b, T (*d)[3]) {
  if (deg < 1) return;
  const T c1 = T(SH_C1);
  b[0] = -c1 * y;
  b[1] = c1 * z;
  b[2] = -c1 * x;
  if (d) {
    for (int k = 0; k < 3; ++k) d[k][0] = d[k][1] = d[k][2] = T(0);
    d[0][1] = -c1;
    d[1][2] = c1;
    d[2][0] = -c1;
  }
  if (deg < 2) return;
  const T xx = x * x, yy = y * y, zz = z * z;
  b[3] = T(SH_C2[0]) * x * y;
  b[4] = T(SH_C2[1]) * y * z;
  b[5] = T(SH_C2[2]) * (T(2) * zz - xx - yy);
  b[6] = T(SH_C2[3]) * x * z;
  b[7] = T(SH_C2[4]) * (xx - yy);
  if (d) {
    const T q0 = T(SH_C2[0]), q1 = T(SH_C2[1]), q2 = T(SH_C2[2]), q3 = T(SH_C2[3]);
    const T q4 = T(SH_C2[4]);
    T dd[5][3] = {{q0 * y, q0 * x, T(0)}, {T(0), q1 * z, q1 * y},
                  {T(-2) * q2 * x, T(-2) * q2 * y, T(4) * q2 * z}, {q3 * z, T(0), q3 * x},
                  {T(2) * q4 * x, T(-2) * q4 * y, T(0)}};
    for (int k = 0; k < 5; ++k)
      for (int j = 0; j < 3; ++j) d[3 + k][j] = dd[k][j];
  }
  if (deg < 3) return;
  const T k0 = T(SH_C3[0]), k1 = T(SH_C3[1]), k2 = T(SH_C3[2]), k3 = T(SH_C3[3]);
  const T k4 = T(SH_C3[4]), k5 = T(SH_C3[5]), k6 = T(SH_C3[6]);
  b[8] = k0 * y * (T(3) * xx - yy);
  b[9] = k1 * x * y * z;
  b[10] = k2 * y * (T(4) * zz - xx - yy);
  b[11] = k3 * z * (T(2) * zz - T(3) * xx - T(3) * yy);
  b[12] = k4 * x * (T(4) * zz - xx - yy);
  b[13] = k5 * z * (xx - yy);
  b[14] = k6 * x * (xx - T(3) * yy);
  if (d) {
    T dd[7][3] = {
        {k0 * T(6) * x * y, k0 * (T(3) * xx - T(3) * yy), T(0)},
        {k1 * y * z, k1 * x * z, k1 * x * y},
        {k2 * T(-2) * x * y, k2 * (T(4) * zz - xx - T(3) * yy), k2 * T(8) * y * z},
        {k3 * T(-6) * x * z, k3 * T(-6) * y * z, k3 * (T(6) * zz - T(3) * xx - T(3) * yy)},
        {k4 * (T(4) * zz - T(3) * xx - yy), k4 * T(-2) * x * y, k4 * T(8) * x * z},
        {k5 * T(2) * x * z, k5 * T(-2) * y * z, k5 * (xx - yy)},
        {k6 * (T(3) * xx - T(3) * yy), k6 * T(-6) * x * y, T(0)}};
    for (int k = 0; k < 7; ++k)
      for (int j = 0; j < 3; ++j) d[8 + k][j] = dd[k][j];
  }
}

template <typename T>
struct Cam {
  T R[9], t[3], ctr[3];
  T fx, fy, cx, cy, limx, limy, lowpass, near_z;
  int W, H;
};

// Rotation matrix of the normalised quaternion (w, x, y, z).
template <typename T>
inline void quat_rot(const T* q, T* Rq) {
  const T w = q[0], x = q[1], y = q[2], z = q[3];
  Rq[0] = T(1) - T(2) * (y * y + z * z);
  Rq[1] = T(2) * (x * y - w * z);
  Rq[2] = T(2) * (x * z + w * y);
  Rq[3] = T(2) * (x * y + w * z);
  Rq[4] = T(1) - T(2) * (x * x + z * z);
  Rq[5] = T(2) * (y * z - w * x);
  Rq[6] = T(2) * (x * z - w * y);
  Rq[7] = T(2) * (y * z + w * x);
  Rq[8] = T(1) - T(2) * (x * x + y * y);
}

// Shared forward pieces of one Gaussian's projection (kept for the backward pass).
template <typename T>
struct Geo {
  T pc[3], zc, tx, ty, qn[4], qnorm, Rq[9], s[3], M[9], TJ[6], A[6], a, b, c, det;
  bool ok_det, tx_in, ty_in;
};

template <typename T>
inline void geo_forward(const Cam<T>& cm, const T* p, const T* ls, const T* q, Geo<T>& g) {
  for (int r = 0; r < 3; ++r)
    g.pc[r] = cm.R[3 * r] * p[0] + cm.R[3 * r + 1] * p[1] + cm.R[3 * r + 2] * p[2] + cm.t[r];
  g.zc = std::max(g.pc[2], cm.near_z);
  const T rx = g.pc[0] / g.zc, ry = g.pc[1] / g.zc;
  g.tx_in = rx >= -cm.limx && rx <= cm.limx;
  g.ty_in = ry >= -cm.limy && ry <= cm.limy;
  g.tx = std::min(std::max(rx, -cm.limx), cm.limx);
  g.ty = std::min(std::max(ry, -cm.limy), cm.limy);
  g.qnorm = std::max(std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]),
                     T(1e-12));
  for (int k = 0; k < 4; ++k) g.qn[k] = q[k] / g.qnorm;
  quat_rot(g.qn, g.Rq);
  for (int k = 0; k < 3; ++k) g.s[k] = std::exp(ls[k]);
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k) g.M[3 * r + k] = g.Rq[3 * r + k] * g.s[k];
  // J = [[fx/z, 0, -fx tx/z], [0, fy/z, -fy ty/z]]; TJ = J R
  const T j00 = cm.fx / g.zc, j02 = -cm.fx * g.tx / g.zc;
  const T j11 = cm.fy / g.zc, j12 = -cm.fy * g.ty / g.zc;
  for (int k = 0; k < 3; ++k) {
    g.TJ[k] = j00 * cm.R[k] + j02 * cm.R[6 + k];
    g.TJ[3 + k] = j11 * cm.R[3 + k] + j12 * cm.R[6 + k];
  }
  for (int r = 0; r < 2; ++r)
    for (int k = 0; k < 3; ++k)
      g.A[3 * r + k] = g.TJ[3 * r] * g.M[k] + g.TJ[3 * r + 1] * g.M[3 + k] +
                       g.TJ[3 * r + 2] * g.M[6 + k];
  g.a = g.A[0] * g.A[0] + g.A[1] * g.A[1] + g.A[2] * g.A[2] + cm.lowpass;
  g.b = g.A[0] * g.A[3] + g.A[1] * g.A[4] + g.A[2] * g.A[5];
  g.c = g.A[3] * g.A[3] + g.A[4] * g.A[4] + g.A[5] * g.A[5] + cm.lowpass;
  g.det = g.a * g.c - g.b * g.b;
  g.ok_det = g.det > T(1e-12);
}

template <typename T>
void project_forward(int64_t n, const Cam<T>& cm, int deg, const T* means, const T* ls,
                     const T* quats, const T* sh_dc, const T* sh_rest, int n_rest, T* m2,
                     T* con, T* depth, int64_t* radii, T* col) {
  for (int64_t i = 0; i < n; ++i) {
    Geo<T> g;
    geo_forward(cm, means + 3 * i, ls + 3 * i, quats + 4 * i, g);
    const T det_s = g.ok_det ? g.det : T(1);
    con[3 * i] = g.c / det_s;
    con[3 * i + 1] = -g.b / det_s;
    con[3 * i + 2] = g.a / det_s;
    const T u = cm.fx * g.pc[0] / g.zc + cm.cx, v = cm.fy * g.pc[1] / g.zc + cm.cy;
    m2[2 * i] = u;
    m2[2 * i + 1] = v;
    depth[i] = g.pc[2];
    const T mid = T(0.5) * (g.a + g.c);
    const T lam = mid + std::sqrt(std::max(mid * mid - g.det, T(0.1)));
    const T rad = std::ceil(T(3) * std::sqrt(lam));
    const bool inside = (u + rad > T(-0.5)) && (u - rad < T(cm.W) - T(0.5)) &&
                        (v + rad > T(-0.5)) && (v - rad < T(cm.H) - T(0.5));
    const bool keep = g.pc[2] > cm.near_z && g.ok_det && inside && std::isfinite(u) &&
                      std::isfinite(v) && std::isfinite(rad);
    radii[i] = keep ? int64_t(rad) : 0;
    // colour: SH at the direction from the camera centre
    T dir[3] = {means[3 * i] - cm.ctr[0], means[3 * i + 1] - cm.ctr[1],
                means[3 * i + 2] - cm.ctr[2]};
    const T dn = std::max(std::sqrt(dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]),
                          T(1e-12));
    T basis[15];
    sh_basis<T>(deg, dir[0] / dn, dir[1] / dn, dir[2] / dn, basis, nullptr);
    const int nb = (deg + 1) * (deg + 1) - 1;
    for (int ch = 0; ch < 3; ++ch) {
      T r = T(SH_C0) * sh_dc[3 * i + ch];
      for (int k = 0; k < nb; ++k) r += basis[k] * sh_rest[(i * n_rest + k) * 3 + ch];
      col[3 * i + ch] = std::max(r + T(0.5), T(0));
    }
  }
}

template <typename T>
void project_backward(int64_t n, const Cam<T>& cm, int deg, const T* means, const T* ls,
                      const T* quats, const T* sh_dc, const T* sh_rest, int n_rest,
                      const int64_t* radii, const T* g_m2, const T* g_con, const T* g_col,
                      T* d_means, T* d_ls, T* d_quats, T* d_dc, T* d_rest) {
  const int nb = (deg + 1) * (deg + 1) - 1;
  for (int64_t i = 0; i < n; ++i) {
    T gp[3] = {T(0), T(0), T(0)};  // d L / d mean
    // ---- colour
    T dir[3] = {means[3 * i] - cm.ctr[0], means[3 * i + 1] - cm.ctr[1],
                means[3 * i + 2] - cm.ctr[2]};
    const T dlen = std::sqrt(dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]);
    const T dn = std::max(dlen, T(1e-12));
    const T ux = dir[0] / dn, uy = dir[1] / dn, uz = dir[2] / dn;
    T basis[15], dbasis[15][3];
    sh_basis<T>(deg, ux, uy, uz, basis, dbasis);
    T gres[3];
    bool any_col = false;
    for (int ch = 0; ch < 3; ++ch) {
      T r = T(SH_C0) * sh_dc[3 * i + ch];
      for (int k = 0; k < nb; ++k) r += basis[k] * sh_rest[(i * n_rest + k) * 3 + ch];
      gres[ch] = (r + T(0.5) >= T(0)) ? g_col[3 * i + ch] : T(0);
      any_col = any_col || gres[ch] != T(0);
      d_dc[3 * i + ch] = T(SH_C0) * gres[ch];
    }
    if (any_col) {
      T gu[3] = {T(0), T(0), T(0)};
      for (int k = 0; k < nb; ++k) {
        T gk = T(0);
        for (int ch = 0; ch < 3; ++ch) {
          d_rest[(i * n_rest + k) * 3 + ch] = basis[k] * gres[ch];
          gk += sh_rest[(i * n_rest + k) * 3 + ch] * gres[ch];
        }
        for (int j = 0; j < 3; ++j) gu[j] += gk * dbasis[k][j];
      }
      if (nb > 0) {
        if (dlen > T(1e-12)) {
          const T dotv = gu[0] * ux + gu[1] * uy + gu[2] * uz;
          gp[0] += (gu[0] - ux * dotv) / dn;
          gp[1] += (gu[1] - uy * dotv) / dn;
          gp[2] += (gu[2] - uz * dotv) / dn;
        } else {
          for (int j = 0; j < 3; ++j) gp[j] += gu[j] / dn;
        }
      }
    }
    // ---- geometry (a culled Gaussian gets gradients too, as under autograd; they are zero
    // when the compositing never used it)
    const T gm0 = g_m2[2 * i], gm1 = g_m2[2 * i + 1];
    const T g0 = g_con[3 * i], g1 = g_con[3 * i + 1], g2 = g_con[3 * i + 2];
    if (gm0 == T(0) && gm1 == T(0) && g0 == T(0) && g1 == T(0) && g2 == T(0)) {
      if (any_col) {
        for (int r = 0; r < 3; ++r) d_means[3 * i + r] = gp[r];
      }
      continue;
    }
    Geo<T> g;
    geo_forward(cm, means + 3 * i, ls + 3 * i, quats + 4 * i, g);
    T ga, gb, gc;
    if (g.ok_det) {
      const T id = T(1) / g.det;
      const T gdet = -(g0 * g.c - g1 * g.b + g2 * g.a) * id * id;
      ga = g2 * id + gdet * g.c;
      gc = g0 * id + gdet * g.a;
      gb = -g1 * id - T(2) * gdet * g.b;
    } else {
      ga = g2;
      gc = g0;
      gb = -g1;
    }
    T gA[6];
    for (int k = 0; k < 3; ++k) {
      gA[k] = T(2) * ga * g.A[k] + gb * g.A[3 + k];
      gA[3 + k] = T(2) * gc * g.A[3 + k] + gb * g.A[k];
    }
    // A = TJ M: gTJ = gA M^T, gM = TJ^T gA
    T gTJ[6], gM[9];
    for (int r = 0; r < 2; ++r)
      for (int k = 0; k < 3; ++k)
        gTJ[3 * r + k] = gA[3 * r] * g.M[3 * k] + gA[3 * r + 1] * g.M[3 * k + 1] +
                         gA[3 * r + 2] * g.M[3 * k + 2];
    for (int r = 0; r < 3; ++r)
      for (int k = 0; k < 3; ++k) gM[3 * r + k] = g.TJ[r] * gA[k] + g.TJ[3 + r] * gA[3 + k];
    // M = Rq diag(s)
    T gR[9];
    for (int k = 0; k < 3; ++k) {
      T gs = T(0);
      for (int r = 0; r < 3; ++r) {
        gR[3 * r + k] = gM[3 * r + k] * g.s[k];
        gs += gM[3 * r + k] * g.Rq[3 * r + k];
      }
      d_ls[3 * i + k] = gs * g.s[k];
    }
    const T w = g.qn[0], x = g.qn[1], y = g.qn[2], z = g.qn[3];
    T gq[4];
    gq[0] = T(2) * (-z * gR[1] + y * gR[2] + z * gR[3] - x * gR[5] - y * gR[6] + x * gR[7]);
    gq[1] = T(2) * (y * gR[1] + z * gR[2] + y * gR[3] - T(2) * x * gR[4] - w * gR[5] +
                    z * gR[6] + w * gR[7] - T(2) * x * gR[8]);
    gq[2] = T(2) * (-T(2) * y * gR[0] + x * gR[1] + w * gR[2] + x * gR[3] + z * gR[5] -
                    w * gR[6] + z * gR[7] - T(2) * y * gR[8]);
    gq[3] = T(2) * (-T(2) * z * gR[0] - w * gR[1] + x * gR[2] + w * gR[3] - T(2) * z * gR[4] +
                    y * gR[5] + x * gR[6] + y * gR[7]);
    const T qd = gq[0] * g.qn[0] + gq[1] * g.qn[1] + gq[2] * g.qn[2] + gq[3] * g.qn[3];
    const bool qclamped = !(g.qnorm > T(1e-12));
    for (int k = 0; k < 4; ++k)
      d_quats[4 * i + k] = (qclamped ? gq[k] : gq[k] - g.qn[k] * qd) / g.qnorm;
    // TJ = J R: gJ = gTJ R^T (only the non-zero entries of J matter)
    const T gj00 = gTJ[0] * cm.R[0] + gTJ[1] * cm.R[1] + gTJ[2] * cm.R[2];
    const T gj02 = gTJ[0] * cm.R[6] + gTJ[1] * cm.R[7] + gTJ[2] * cm.R[8];
    const T gj11 = gTJ[3] * cm.R[3] + gTJ[4] * cm.R[4] + gTJ[5] * cm.R[5];
    const T gj12 = gTJ[3] * cm.R[6] + gTJ[4] * cm.R[7] + gTJ[5] * cm.R[8];
    const T zc = g.zc, iz = T(1) / zc, iz2 = iz * iz;
    T gzc = -gj00 * cm.fx * iz2 + gj02 * cm.fx * g.tx * iz2 - gj11 * cm.fy * iz2 +
            gj12 * cm.fy * g.ty * iz2;
    const T gtx = -gj02 * cm.fx * iz, gty = -gj12 * cm.fy * iz;
    T gpc[3] = {T(0), T(0), T(0)};
    if (g.tx_in) {
      gpc[0] += gtx * iz;
      gzc -= gtx * g.pc[0] * iz2;
    }
    if (g.ty_in) {
      gpc[1] += gty * iz;
      gzc -= gty * g.pc[1] * iz2;
    }
    gpc[0] += gm0 * cm.fx * iz;
    gpc[1] += gm1 * cm.fy * iz;
    gzc -= (gm0 * cm.fx * g.pc[0] + gm1 * cm.fy * g.pc[1]) * iz2;
    if (g.pc[2] >= cm.near_z) gpc[2] += gzc;
    for (int r = 0; r < 3; ++r)
      d_means[3 * i + r] =
          gp[r] + cm.R[r] * gpc[0] + cm.R[3 + r] * gpc[1] + cm.R[6 + r] * gpc[2];
    (void)radii;
  }
}

template <typename T>
Cam<T> make_cam(const double* cam, int W, int H) {
  // cam: R (9), t (3), centre (3), fx, fy, cx, cy, limx, limy, lowpass, near
  Cam<T> c;
  for (int k = 0; k < 9; ++k) c.R[k] = T(cam[k]);
  for (int k = 0; k < 3; ++k) {
    c.t[k] = T(cam[9 + k]);
    c.ctr[k] = T(cam[12 + k]);
  }
  c.fx = T(cam[15]);
  c.fy = T(cam[16]);
  c.cx = T(cam[17]);
  c.cy = T(cam[18]);
  c.limx = T(cam[19]);
  c.limy = T(cam[20]);
  c.lowpass = T(cam[21]);
  c.near_z = T(cam[22]);
  c.W = W;
  c.H = H;
  return c;
}


// ------------------------------------------------------------------ masked SSIM (loss term)

// 1-D Gaussian blur of K interleaved channels along one axis with replicate padding:
// out[i] = sum_k g[k] in[clamp(i + k - r)]. ``n`` positions along the axis, ``stride`` between
// them, ``lines`` independent lines ``lstride`` apart.
template <typename T>
void blur_axis(const T* in, T* out, int n, int64_t stride, int lines, int64_t lstride, int K,
               const T* g, int r) {
  for (int l = 0; l < lines; ++l) {
    const T* src = in + l * lstride;
    T* dst = out + l * lstride;
    for (int i = 0; i < n; ++i) {
      T* o = dst + i * stride;
      for (int c = 0; c < K; ++c) o[c] = T(0);
      for (int k = -r; k <= r; ++k) {
        const int j = std::min(std::max(i + k, 0), n - 1);
        const T w = g[k + r];
        const T* s = src + j * stride;
        for (int c = 0; c < K; ++c) o[c] += w * s[c];
      }
    }
  }
}

// The transpose of blur_axis (scatter instead of gather).
template <typename T>
void blur_axis_t(const T* in, T* out, int n, int64_t stride, int lines, int64_t lstride, int K,
                 const T* g, int r) {
  for (int l = 0; l < lines; ++l) {
    const T* src = in + l * lstride;
    T* dst = out + l * lstride;
    for (int i = 0; i < n; ++i)
      for (int c = 0; c < K; ++c) dst[i * stride + c] = T(0);
    for (int i = 0; i < n; ++i) {
      const T* s = src + i * stride;
      for (int k = -r; k <= r; ++k) {
        const int j = std::min(std::max(i + k, 0), n - 1);
        const T w = g[k + r];
        T* o = dst + j * stride;
        for (int c = 0; c < K; ++c) o[c] += w * s[c];
      }
    }
  }
}

// Separable 2-D blur (or its transpose) of an [H, W, K] image; ``tmp`` is scratch of its size.
template <typename T>
void blur2d(const T* in, T* out, T* tmp, int H, int W, int K, const T* g, int r, bool transpose) {
  const int64_t row = int64_t(W) * K;
  if (!transpose) {
    blur_axis(in, tmp, W, K, H, row, K, g, r);    // along x
    blur_axis(tmp, out, H, row, 1, 0, int(row), g, r);  // along y (whole rows at once)
  } else {
    blur_axis_t(in, tmp, H, row, 1, 0, int(row), g, r);
    blur_axis_t(tmp, out, W, K, H, row, K, g, r);
  }
}

// Per channel of an [H, W, 3] pair: the 5 blurred moments (mx, my, exx, eyy, exy) -> [H, W, 15]
template <typename T>
void ssim_moments(int H, int W, const T* x, const T* y, const T* g, int r, T* mom, T* tmp) {
  const int64_t n = int64_t(H) * W;
  for (int64_t p = 0; p < n; ++p)
    for (int c = 0; c < 3; ++c) {
      const T a = x[3 * p + c], b = y[3 * p + c];
      T* m = mom + 15 * p + 5 * c;
      m[0] = a;
      m[1] = b;
      m[2] = a * a;
      m[3] = b * b;
      m[4] = a * b;
    }
  T* blurred = tmp + 15 * n;
  blur2d(mom, blurred, tmp, H, W, 15, g, r, false);
  std::copy(blurred, blurred + 15 * n, mom);
}

// Mean over mask pixels of the per-pixel SSIM (mean over the 3 channels); ``mom`` receives the
// blurred moments for the backward pass. tmp: scratch of 30 H W values.
template <typename T>
double ssim_forward(int H, int W, const T* x, const T* y, const uint8_t* mask, const T* g,
                    int r, T c1, T c2, T* mom, T* tmp) {
  ssim_moments(H, W, x, y, g, r, mom, tmp);
  const int64_t n = int64_t(H) * W;
  double total = 0.0;
  int64_t count = 0;
  for (int64_t p = 0; p < n; ++p) {
    if (!mask[p]) continue;
    ++count;
    T s = T(0);
    for (int c = 0; c < 3; ++c) {
      const T* m = mom + 15 * p + 5 * c;
      const T mx = m[0], my = m[1];
      const T sxx = m[2] - mx * mx, syy = m[3] - my * my, sxy = m[4] - mx * my;
      s += ((T(2) * mx * my + c1) * (T(2) * sxy + c2)) /
           ((mx * mx + my * my + c1) * (sxx + syy + c2));
    }
    total += double(s) / 3.0;
  }
  return count > 0 ? total / double(count) : 0.0;
}

// d (masked mean SSIM) / d x, times ``grad_out``; tmp: scratch of 27 H W values.
template <typename T>
void ssim_backward(int H, int W, const T* x, const T* y, const uint8_t* mask, const T* g, int r,
                   T c1, T c2, const T* mom, T grad_out, T* dx, T* tmp) {
  const int64_t n = int64_t(H) * W;
  int64_t count = 0;
  for (int64_t p = 0; p < n; ++p) count += mask[p] ? 1 : 0;
  T* q = tmp;           // [H, W, 9]: d mx, d exx, d exy per channel
  T* back = tmp + 9 * n;  // [H, W, 9]
  T* scratch = tmp + 18 * n;
  const T w = count > 0 ? grad_out / (T(3) * T(count)) : T(0);
  for (int64_t p = 0; p < n; ++p) {
    T* o = q + 9 * p;
    if (!mask[p]) {
      for (int k = 0; k < 9; ++k) o[k] = T(0);
      continue;
    }
    for (int c = 0; c < 3; ++c) {
      const T* m = mom + 15 * p + 5 * c;
      const T mx = m[0], my = m[1];
      const T sxx = m[2] - mx * mx, syy = m[3] - my * my, sxy = m[4] - mx * my;
      const T a1 = T(2) * mx * my + c1, a2 = T(2) * sxy + c2;
      const T b1 = mx * mx + my * my + c1, b2 = sxx + syy + c2;
      const T den = b1 * b2;
      const T s = a1 * a2 / den;
      const T d_a1 = a2 / den, d_a2 = a1 / den, d_b1 = -s / b1, d_b2 = -s / b2;
      o[3 * c] = w * (T(2) * my * (d_a1 - d_a2) + T(2) * mx * (d_b1 - d_b2));
      o[3 * c + 1] = w * d_b2;
      o[3 * c + 2] = w * T(2) * d_a2;
    }
  }
  blur2d(q, back, scratch, H, W, 9, g, r, true);
  for (int64_t p = 0; p < n; ++p)
    for (int c = 0; c < 3; ++c) {
      const T* b = back + 9 * p + 3 * c;
      dx[3 * p + c] = b[0] + T(2) * x[3 * p + c] * b[1] + y[3 * p + c] * b[2];
    }
}

}  // namespace

extern "C" {

int ooi_kernel_version() { return 3; }

#define OOI_DEFINE(SUFFIX, T)                                                                 \
  void ooi_forward_##SUFFIX(int W, int H, int tiles_x, int64_t n_tiles,                      \
                            const int64_t* tile_start, const int64_t* gid, const T* m2,      \
                            const T* con, const T* op, const T* col, double alpha_max,       \
                            double alpha_min, double t_min, T* out_col, T* out_t,            \
                            int32_t* out_n) {                                                \
    forward<T>(W, H, tiles_x, n_tiles, tile_start, gid, m2, con, op, col, T(alpha_max),      \
               T(alpha_min), T(t_min), out_col, out_t, out_n);                               \
  }                                                                                          \
  void ooi_backward_##SUFFIX(int W, int H, int tiles_x, int64_t n_tiles,                     \
                             const int64_t* tile_start, const int64_t* gid, const T* m2,     \
                             const T* con, const T* op, const T* col, double alpha_max,      \
                             double alpha_min, const T* fin_t, const int32_t* n_contrib,     \
                             const T* g_col, const T* g_acc, T* grad) {                      \
    backward<T>(W, H, tiles_x, n_tiles, tile_start, gid, m2, con, op, col, T(alpha_max),     \
                T(alpha_min), fin_t, n_contrib, g_col, g_acc, grad);                         \
  }                                                                                          \
  void ooi_project_forward_##SUFFIX(int64_t n, const double* cam, int W, int H, int deg,     \
                                    const T* means, const T* ls, const T* quats,            \
                                    const T* sh_dc, const T* sh_rest, int n_rest, T* m2,    \
                                    T* con, T* depth, int64_t* radii, T* col) {             \
    project_forward<T>(n, make_cam<T>(cam, W, H), deg, means, ls, quats, sh_dc, sh_rest,     \
                       n_rest, m2, con, depth, radii, col);                                  \
  }                                                                                          \
  void ooi_project_backward_##SUFFIX(int64_t n, const double* cam, int W, int H, int deg,    \
                                     const T* means, const T* ls, const T* quats,           \
                                     const T* sh_dc, const T* sh_rest, int n_rest,          \
                                     const int64_t* radii, const T* g_m2, const T* g_con,   \
                                     const T* g_col, T* d_means, T* d_ls, T* d_quats,       \
                                     T* d_dc, T* d_rest) {                                  \
    project_backward<T>(n, make_cam<T>(cam, W, H), deg, means, ls, quats, sh_dc, sh_rest,    \
                        n_rest, radii, g_m2, g_con, g_col, d_means, d_ls, d_quats, d_dc,     \
                        d_rest);                                                             \
  }                                                                                          \
  double ooi_ssim_forward_##SUFFIX(int H, int W, const T* x, const T* y, const uint8_t* mask,  \
                                   const T* g, int r, double c1, double c2, T* mom,         \
                                   T* tmp) {                                                \
    return ssim_forward<T>(H, W, x, y, mask, g, r, T(c1), T(c2), mom, tmp);                  \
  }                                                                                          \
  void ooi_ssim_backward_##SUFFIX(int H, int W, const T* x, const T* y, const uint8_t* mask,   \
                                  const T* g, int r, double c1, double c2, const T* mom,     \
                                  double grad_out, T* dx, T* tmp) {                          \
    ssim_backward<T>(H, W, x, y, mask, g, r, T(c1), T(c2), mom, T(grad_out), dx, tmp);       \
  }

OOI_DEFINE(f32, float)
OOI_DEFINE(f64, double)
}
"""

# -ffp-contract=off: forward and backward must take the same alpha decisions bit for bit
_FLAGS = ["-O3", "-std=c++17", "-shared", "-fPIC", "-ffp-contract=off", "-fno-math-errno"]

_lock = threading.Lock()
_lib: Optional[ctypes.CDLL] = None
_tried = False
_why_not = ""


def _cpu_key() -> str:
    """CPU identity for the cache key (the build uses -march=native)."""
    info = platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(("model name", "flags")):
                    info += line
                if info.count("\n") >= 2:
                    break
    except OSError:
        pass
    return info


def cache_dir() -> Path:
    """Where built libraries live ($OOI_SEG_KERNEL_DIR, else ~/.cache/ooi_seg_ros/kernels)."""
    env = os.environ.get("OOI_SEG_KERNEL_DIR")
    return Path(env) if env else Path.home() / ".cache" / "ooi_seg_ros" / "kernels"


def _compiler() -> Optional[str]:
    return os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++") \
        or shutil.which("clang++")


def _build(cxx: str) -> Path:
    flags = _FLAGS + ["-march=native"]
    key = hashlib.sha256("\0".join([_SOURCE, " ".join(flags), cxx, _cpu_key()]).encode())
    out = cache_dir() / f"ooi_composite_{key.hexdigest()[:16]}.so"
    if out.is_file():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
        src = Path(tmp) / "composite.cpp"
        src.write_text(_SOURCE)
        lib = Path(tmp) / out.name
        cmd = [cxx, *flags, str(src), "-o", str(lib)]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        if res.returncode != 0 and "-march=native" in cmd:  # e.g. a compiler without it
            cmd.remove("-march=native")
            res = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        if res.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed: {res.stderr.strip()[-500:]}")
        os.replace(lib, out)  # atomic: concurrent builders never see a half-written file
    return out


def _bind(path: Path) -> ctypes.CDLL:
    lib = ctypes.CDLL(str(path))
    p, i, i64, d = ctypes.c_void_p, ctypes.c_int, ctypes.c_int64, ctypes.c_double
    for sfx in ("f32", "f64"):
        fwd = getattr(lib, f"ooi_forward_{sfx}")
        fwd.argtypes = [i, i, i, i64, p, p, p, p, p, p, d, d, d, p, p, p]
        fwd.restype = None
        bwd = getattr(lib, f"ooi_backward_{sfx}")
        bwd.argtypes = [i, i, i, i64, p, p, p, p, p, p, d, d, p, p, p, p, p]
        bwd.restype = None
        pf = getattr(lib, f"ooi_project_forward_{sfx}")
        pf.argtypes = [i64, p, i, i, i, p, p, p, p, p, i, p, p, p, p, p]
        pf.restype = None
        pb = getattr(lib, f"ooi_project_backward_{sfx}")
        pb.argtypes = [i64, p, i, i, i, p, p, p, p, p, i, p, p, p, p, p, p, p, p, p]
        pb.restype = None
        sf = getattr(lib, f"ooi_ssim_forward_{sfx}")
        sf.argtypes = [i, i, p, p, p, p, i, d, d, p, p]
        sf.restype = d
        sb = getattr(lib, f"ooi_ssim_backward_{sfx}")
        sb.argtypes = [i, i, p, p, p, p, i, d, d, p, d, p, p]
        sb.restype = None
    return lib


def load() -> Optional[ctypes.CDLL]:
    """The compiled kernel library, building it on first use; None (logged once) if impossible."""
    global _lib, _tried, _why_not
    if os.environ.get("OOI_SEG_NO_KERNEL", "") not in ("", "0"):
        return None
    with _lock:
        if _tried:
            return _lib
        _tried = True
        cxx = _compiler()
        try:
            if cxx is None:
                raise RuntimeError("no C++ compiler (g++, c++ or clang++) on PATH")
            _lib = _bind(_build(cxx))
        except (RuntimeError, OSError, subprocess.SubprocessError, AttributeError) as exc:
            _why_not = str(exc)
            log.warning("compiled rasteriser kernel unavailable, using the (slower) pure-torch "
                        "path: %s", _why_not)
            _lib = None
        return _lib


def available() -> bool:
    """True when the compiled kernel can be used."""
    return load() is not None


def unavailable_reason() -> str:
    """Why ``load()`` returned None ('' when it did not, or was not tried)."""
    return _why_not


def _ptr(t: torch.Tensor) -> int:
    return t.data_ptr()


class CompositeFn(torch.autograd.Function):
    """Tile compositing through the compiled kernel.

    Inputs: means2d [N, 2], conics [N, 3], opacities [N], colours [N, 3] (one float dtype),
    ``gid`` [P] int64 Gaussian ids sorted by tile then depth, ``tile_start`` [T + 1] int64.
    Returns colour [H, W, 3] without background and accumulated alpha [H, W].
    """

    @staticmethod
    def forward(ctx, m2, con, op, col, gid, tile_start, width, height, tiles_x):
        lib = load()
        dt = m2.dtype
        m2, con, op, col = (t.detach().contiguous() for t in (m2, con, op, col))
        gid, tile_start = gid.contiguous(), tile_start.contiguous()
        out_col = torch.zeros(height, width, 3, dtype=dt)
        out_t = torch.ones(height, width, dtype=dt)
        out_n = torch.zeros(height, width, dtype=torch.int32)
        fn = lib.ooi_forward_f64 if dt == torch.float64 else lib.ooi_forward_f32
        fn(width, height, tiles_x, len(tile_start) - 1, _ptr(tile_start), _ptr(gid), _ptr(m2),
           _ptr(con), _ptr(op), _ptr(col), ALPHA_MAX, ALPHA_MIN, T_MIN, _ptr(out_col),
           _ptr(out_t), _ptr(out_n))
        ctx.save_for_backward(m2, con, op, col, gid, tile_start, out_t, out_n)
        ctx.dims = (width, height, tiles_x)
        return out_col, 1.0 - out_t

    @staticmethod
    def backward(ctx, g_col, g_acc):
        lib = load()
        m2, con, op, col, gid, tile_start, out_t, out_n = ctx.saved_tensors
        width, height, tiles_x = ctx.dims
        dt = m2.dtype
        g_col = (torch.zeros(height, width, 3, dtype=dt) if g_col is None
                 else g_col.to(dt).contiguous())
        g_acc = (torch.zeros(height, width, dtype=dt) if g_acc is None
                 else g_acc.to(dt).contiguous())
        grad = torch.zeros(len(m2), N_PAIR_GRADS, dtype=dt)
        fn = lib.ooi_backward_f64 if dt == torch.float64 else lib.ooi_backward_f32
        fn(width, height, tiles_x, len(tile_start) - 1, _ptr(tile_start), _ptr(gid), _ptr(m2),
           _ptr(con), _ptr(op), _ptr(col), ALPHA_MAX, ALPHA_MIN, _ptr(out_t), _ptr(out_n),
           _ptr(g_col), _ptr(g_acc), _ptr(grad))
        return (grad[:, 0:2], grad[:, 2:5], grad[:, 5], grad[:, 6:9], None, None, None, None,
                None)


def _cam_array(cam: RasterCamera) -> torch.Tensor:
    """The camera as the kernel reads it: R (9), t (3), centre (3), fx, fy, cx, cy, limx,
    limy, lowpass, near, as float64 (values taken from the camera's own dtype, like the torch
    path)."""
    limx = 1.3 * max(cam.cx, cam.width - cam.cx) / cam.fx
    limy = 1.3 * max(cam.cy, cam.height - cam.cy) / cam.fy
    head = torch.cat([cam.R.reshape(-1), cam.t.reshape(-1), cam.center.reshape(-1)])
    tail = torch.tensor([cam.fx, cam.fy, cam.cx, cam.cy, limx, limy, cam.lowpass, NEAR],
                        dtype=torch.float64)
    return torch.cat([head.detach().to(torch.float64), tail]).contiguous()


class ProjectFn(torch.autograd.Function):
    """EWA projection + SH colour of every Gaussian through the compiled kernel.

    Same values and gradients as ``raster_common.project`` (tests), returned as
    (means2d [N, 2], conics [N, 3], depths [N], radii [N] int64, colours [N, 3]); depths and
    radii carry no gradient.
    """

    @staticmethod
    def forward(ctx, means, log_scales, quats, sh_dc, sh_rest, cam_arr, width, height, degree):
        lib = load()
        dt = means.dtype
        params = (means, log_scales, quats, sh_dc, sh_rest)
        ins = [t.detach().to(dt).contiguous() for t in params]
        n = len(means)
        n_rest = ins[4].shape[1] if ins[4].dim() == 3 else 0
        deg = min(degree, int(round((n_rest + 1) ** 0.5)) - 1)
        m2 = torch.empty(n, 2, dtype=dt)
        con = torch.empty(n, 3, dtype=dt)
        depth = torch.empty(n, dtype=dt)
        radii = torch.empty(n, dtype=torch.int64)
        col = torch.empty(n, 3, dtype=dt)
        fn = lib.ooi_project_forward_f64 if dt == torch.float64 else lib.ooi_project_forward_f32
        fn(n, _ptr(cam_arr), width, height, deg, *(_ptr(t) for t in ins), n_rest, _ptr(m2),
           _ptr(con), _ptr(depth), _ptr(radii), _ptr(col))
        ctx.save_for_backward(*ins, cam_arr, radii)
        ctx.dims = (width, height, deg, n_rest)
        ctx.mark_non_differentiable(depth, radii)
        return m2, con, depth, radii, col

    @staticmethod
    def backward(ctx, g_m2, g_con, g_depth, g_radii, g_col):
        lib = load()
        means, log_scales, quats, sh_dc, sh_rest, cam_arr, radii = ctx.saved_tensors
        width, height, deg, n_rest = ctx.dims
        dt, n = means.dtype, len(means)

        def grad_or_zero(g: Optional[torch.Tensor], cols: int) -> torch.Tensor:
            return (torch.zeros(n, cols, dtype=dt) if g is None
                    else g.to(dt).contiguous())

        g_m2, g_con, g_col = grad_or_zero(g_m2, 2), grad_or_zero(g_con, 3), grad_or_zero(g_col, 3)
        d = [torch.zeros_like(t) for t in (means, log_scales, quats, sh_dc, sh_rest)]
        fn = (lib.ooi_project_backward_f64 if dt == torch.float64
              else lib.ooi_project_backward_f32)
        fn(n, _ptr(cam_arr), width, height, deg, _ptr(means), _ptr(log_scales), _ptr(quats),
           _ptr(sh_dc), _ptr(sh_rest), n_rest, _ptr(radii), _ptr(g_m2), _ptr(g_con),
           _ptr(g_col), *(_ptr(t) for t in d))
        return (*d, None, None, None, None)


def project(means: torch.Tensor, log_scales: torch.Tensor, quats: torch.Tensor,
            logit_opacities: torch.Tensor, sh_dc: torch.Tensor, sh_rest: torch.Tensor,
            cam: RasterCamera, sh_degree: int) -> Projected:
    """``raster_common.project`` through the compiled kernel (requires ``available()``)."""
    m2, con, depth, radii, col = ProjectFn.apply(means, log_scales, quats, sh_dc, sh_rest,
                                                 _cam_array(cam), int(cam.width),
                                                 int(cam.height), int(sh_degree))
    return Projected(m2, con, depth, radii, col, torch.sigmoid(logit_opacities))


SSIM_C1, SSIM_C2 = 0.01 ** 2, 0.03 ** 2


class MaskedSsimFn(torch.autograd.Function):
    """Mean over mask pixels of the per-pixel SSIM (Gaussian window, replicate padding, mean
    over the 3 channels) of ``x`` against ``y`` (no gradient), as ``loss.ssim_map`` followed
    by ``loss.masked_mean``, in one compiled pass forward and one backward."""

    @staticmethod
    def forward(ctx, x, y, mask, window):
        lib = load()
        dt = x.dtype
        x = x.detach().contiguous()
        y = y.detach().to(dt).contiguous()
        m = mask.to(torch.uint8).contiguous()
        g = window.to(dt).contiguous()
        h, w = x.shape[:2]
        mom = torch.empty(h, w, 15, dtype=dt)
        tmp = torch.empty(h, w, 30, dtype=dt)
        fn = lib.ooi_ssim_forward_f64 if dt == torch.float64 else lib.ooi_ssim_forward_f32
        val = fn(h, w, _ptr(x), _ptr(y), _ptr(m), _ptr(g), len(g) // 2, SSIM_C1, SSIM_C2,
                 _ptr(mom), _ptr(tmp))
        ctx.save_for_backward(x, y, m, g, mom)
        return x.new_tensor(val)

    @staticmethod
    def backward(ctx, grad):
        lib = load()
        x, y, m, g, mom = ctx.saved_tensors
        dt = x.dtype
        h, w = x.shape[:2]
        dx = torch.empty_like(x)
        tmp = torch.empty(h, w, 27, dtype=dt)
        fn = lib.ooi_ssim_backward_f64 if dt == torch.float64 else lib.ooi_ssim_backward_f32
        fn(h, w, _ptr(x), _ptr(y), _ptr(m), _ptr(g), len(g) // 2, SSIM_C1, SSIM_C2, _ptr(mom),
           float(grad), _ptr(dx), _ptr(tmp))
        return dx, None, None, None


def masked_ssim(x: torch.Tensor, y: torch.Tensor, mask: torch.Tensor,
                window: torch.Tensor) -> torch.Tensor:
    """Differentiable (in ``x``) mean SSIM over ``mask`` of [H, W, 3] images; ``window`` is the
    normalised 1-D Gaussian of odd length (requires ``available()``)."""
    return MaskedSsimFn.apply(x, y, mask, window)


def composite(m2: torch.Tensor, con: torch.Tensor, op: torch.Tensor, col: torch.Tensor,
              gid: torch.Tensor, tile_start: torch.Tensor, width: int, height: int,
              tiles_x: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Differentiable compositing of sorted tile pairs; see ``CompositeFn``."""
    return CompositeFn.apply(m2, con, op, col, gid, tile_start, width, height, tiles_x)


def main() -> int:
    """Build the kernel now (e.g. a setup step) and print where it is."""
    logging.basicConfig(level=logging.INFO)
    lib = load()
    if lib is None:
        print(f"kernel unavailable: {_why_not}", file=sys.stderr)
        return 1
    print(lib._name)
    return 0


if __name__ == "__main__":
    sys.exit(main())
