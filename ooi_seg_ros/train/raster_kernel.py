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
The backward writes one gradient row per (tile, Gaussian) pair, summed per Gaussian by torch,
so the result does not depend on summation order across tiles.

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

from .raster_common import ALPHA_MAX, ALPHA_MIN, T_MIN

log = logging.getLogger(__name__)

TILE = 16
N_PAIR_GRADS = 9  # per pair: d mean2d (2), d conic (3), d opacity (1), d colour (3)

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
              const T* g_col, const T* g_acc, T* pair_grad) {
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
      T* pg = pair_grad + k * 9;
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
      pg[0] = gmx;
      pg[1] = gmy;
      pg[2] = ga_;
      pg[3] = gb;
      pg[4] = gc_;
      pg[5] = go;
      pg[6] = gr;
      pg[7] = gg_;
      pg[8] = gbl;
    }
  }
}

}  // namespace

extern "C" {

int ooi_kernel_version() { return 1; }

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
                             const T* g_col, const T* g_acc, T* pair_grad) {                 \
    backward<T>(W, H, tiles_x, n_tiles, tile_start, gid, m2, con, op, col, T(alpha_max),     \
                T(alpha_min), fin_t, n_contrib, g_col, g_acc, pair_grad);                    \
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
        pair = torch.zeros(len(gid), N_PAIR_GRADS, dtype=dt)
        fn = lib.ooi_backward_f64 if dt == torch.float64 else lib.ooi_backward_f32
        fn(width, height, tiles_x, len(tile_start) - 1, _ptr(tile_start), _ptr(gid), _ptr(m2),
           _ptr(con), _ptr(op), _ptr(col), ALPHA_MAX, ALPHA_MIN, _ptr(out_t), _ptr(out_n),
           _ptr(g_col), _ptr(g_acc), _ptr(pair))
        grad = torch.zeros(len(m2), N_PAIR_GRADS, dtype=dt).index_add_(0, gid, pair)
        return (grad[:, 0:2], grad[:, 2:5], grad[:, 5], grad[:, 6:9], None, None, None, None,
                None)


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
