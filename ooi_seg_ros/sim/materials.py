"""Procedural materials: colour as a function of the world-space surface point.

A material is a colour ramp driven by multi-octave noise (the texture SIFT keys on), plus the
details real surfaces have: stains/lichen/decal spots, fine grain (grass, asphalt), panel lines
or tile joints on a world grid, paint stripes, and painted markings in world boxes (taxi lines,
cheat lines). Everything is a function of the 3D point, so every view sees the same colours.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .noise import NoiseField

RGB = tuple[float, float, float]


def rgb255(r: int, g: int, b: int) -> RGB:
    """A colour given in 0-255 as the 0-1 floats materials use."""
    return (r / 255.0, g / 255.0, b / 255.0)


@dataclass(frozen=True)
class Decal:
    """Paint inside a world-space box ``lo``..``hi`` (markings, livery stripes)."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    color: RGB
    wear: float = 0.25  # how much the underlying noise shows through (scuffed paint)


@dataclass(frozen=True)
class Material:
    """A procedural surface: noise ramp + spots + grain + grid lines + stripes + decals."""

    colors: tuple[RGB, RGB]  # ramp from dark to light, driven by fbm noise
    scale: float  # metres; wavelength of the coarsest noise octave
    octaves: int = 4  # noise octaves (each halves the feature size)
    contrast: float = 1.0  # >1 stretches the ramp (harder, more contrasty blobs)
    spot_color: Optional[RGB] = None  # stains / lichen / dirt patches
    spot_frac: float = 0.0  # fraction of the surface covered by spots
    spot_scale: float = 0.0  # metres; 0 -> half of ``scale``
    grain: float = 0.0  # amplitude of a fine grain at scale/16 (grass blades, asphalt)
    grid: Optional[tuple[float, float, float]] = None  # (period m, line width m, darkening)
    stripes: Optional[tuple[tuple[float, float, float], float, float, RGB]] = None
    # ^ (axis, period m, duty 0-1, colour): parallel paint stripes / planks
    decals: tuple[Decal, ...] = field(default_factory=tuple)
    seed: int = 0  # decorrelates materials that share a noise field


@dataclass(frozen=True)
class Lighting:
    """Fixed scene lighting: one directional light, hemisphere ambient, optional shadows."""

    direction: tuple[float, float, float] = (0.35, 0.25, 0.9)  # towards the light (world)
    ambient: float = 0.45  # light from everywhere (sky / bounced)
    diffuse: float = 0.65  # strength of the directional light
    shadow: float = 0.55  # fraction of the directional light a shadow removes
    sky_zenith: RGB = (0.42, 0.60, 0.86)
    sky_horizon: RGB = (0.86, 0.89, 0.93)
    clouds: float = 0.5  # cloud cover 0-1 (outdoor sky only)


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3 - 2 * t)


# quantiles of the fbm output (close to normal, mean 0.5, sd ~0.2): frac -> threshold
def _spot_threshold(frac: float) -> float:
    from statistics import NormalDist

    frac = min(max(frac, 1e-4), 1 - 1e-4)
    return 0.5 + 0.2 * NormalDist().inv_cdf(1.0 - frac)


def shade_material(mat: Material, noise: NoiseField, p: np.ndarray,
                   n: np.ndarray) -> np.ndarray:
    """Albedo [N, 3] float32 in [0, 1] of material ``mat`` at world points ``p`` [N, 3].

    ``n`` [N, 3] are unit surface normals (used so that grid lines are drawn only across a
    surface, never on a face that is parallel to the grid plane).
    """
    p = np.asarray(p, np.float32)
    off = np.float32(17.31 * mat.seed)
    t = noise.fbm(p / mat.scale + off, mat.octaves)
    if mat.contrast != 1.0:
        t = np.clip(0.5 + (t - 0.5) * mat.contrast, 0.0, 1.0)
    c0 = np.asarray(mat.colors[0], np.float32)
    c1 = np.asarray(mat.colors[1], np.float32)
    col = c0 + t[:, None] * (c1 - c0)
    if mat.spot_color is not None and mat.spot_frac > 0:
        ss = mat.spot_scale or mat.scale * 0.5
        s = noise.fbm(p / ss + off + 101.0, 3, first_octave=4)
        th = _spot_threshold(mat.spot_frac)
        w = 0.85 * _smoothstep(th - 0.03, th + 0.03, s)[:, None]
        col = col + w * (np.asarray(mat.spot_color, np.float32) - col)
    if mat.grain > 0:
        g = noise.value(p * (16.0 / mat.scale) + off, 7) - 0.5
        col = col * (1.0 + 2.0 * mat.grain * g)[:, None]
    if mat.stripes is not None:
        axis, period, duty, scol = mat.stripes
        u = (p @ np.asarray(axis, np.float32)) / period
        frac = u - np.floor(u)
        w = (_smoothstep(0.0, 0.04, frac) * (1 - _smoothstep(duty - 0.04, duty, frac)))[:, None]
        tint = np.asarray(scol, np.float32) * (0.75 + 0.5 * t[:, None])
        col = col + w * (tint - col)
    if mat.grid is not None:
        period, width, dark = mat.grid
        line = np.zeros(p.shape[0], np.float32)
        for k in range(3):
            across = np.abs(n[:, k]) < 0.7  # surface crosses the grid planes of this axis
            u = p[:, k] / period
            d = np.abs(u - np.round(u)) * period
            line = np.maximum(line, across * (1 - _smoothstep(0.5 * width, width, d)))
        col = col * (1 - dark * line)[:, None]
    for dec in mat.decals:
        lo, hi = dec.lo, dec.hi
        inside = (p[:, 0] >= lo[0]) & (p[:, 0] <= hi[0])
        for k in (1, 2):
            inside &= (p[:, k] >= lo[k]) & (p[:, k] <= hi[k])
        if np.any(inside):
            shade = 1 - dec.wear + dec.wear * 2 * t[inside, None]
            col[inside] = np.asarray(dec.color, np.float32) * shade
    return np.clip(col, 0.0, 1.0)


def sky_color(light: Lighting, noise: NoiseField, d: np.ndarray) -> np.ndarray:
    """Colour [N, 3] of rays ``d`` [N, 3] (unit) that hit nothing: gradient sky with clouds.

    A function of the direction only (the sky is at infinity), so it is view-consistent too.
    """
    d = np.asarray(d, np.float32)
    up = np.clip(d[:, 2], 0.0, 1.0) ** 0.6
    zen = np.asarray(light.sky_zenith, np.float32)
    hor = np.asarray(light.sky_horizon, np.float32)
    col = hor + up[:, None] * (zen - hor)
    if light.clouds > 0:
        c = noise.fbm(d * 4.0 + 333.0, 4)
        w = _smoothstep(0.62 - 0.25 * light.clouds, 0.8, c) * (d[:, 2] > -0.05)
        col = col + w[:, None] * (np.float32(0.96) - col)
    return col
