"""Seeded 3D value noise for view-consistent procedural textures.

Textures are functions of the world-space hit point only, so a surface point gets the same
colour from every camera (what SfM needs to match it). Value noise on a periodic random
lattice is cheap in numpy (eight table look-ups per octave) and gives the blob-like contrast
at several scales that SIFT's difference-of-Gaussians detector responds to.
"""

from __future__ import annotations

import numpy as np

TABLE_BITS = 6
TABLE_SIZE = 1 << TABLE_BITS  # lattice period in cells; octaves are rotated so it never shows
_MASK = TABLE_SIZE - 1


class NoiseField:
    """Multi-octave 3D value noise, deterministic for a seed.

    Each octave uses its own random rotation and offset so that lattice axes and the table
    period do not line up between octaves (no visible grid, no repeats at drone scales).
    """

    def __init__(self, seed: int, max_octaves: int = 8) -> None:
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x5EED]))
        self.table = rng.random(TABLE_SIZE ** 3, dtype=np.float32)  # values in [0, 1)
        self.rot = np.empty((max_octaves, 3, 3), np.float32)
        for k in range(max_octaves):
            q, r = np.linalg.qr(rng.normal(size=(3, 3)))
            q = q * np.sign(np.diag(r))
            self.rot[k] = q.astype(np.float32)
        self.offset = (rng.random((max_octaves, 3)) * TABLE_SIZE).astype(np.float32)

    def value(self, p: np.ndarray, octave: int = 0) -> np.ndarray:
        """Single-octave noise in [0, 1] at points ``p`` [N, 3] (lattice units)."""
        q = np.asarray(p, np.float32) @ self.rot[octave].T + self.offset[octave]
        i = np.floor(q)
        f = q - i
        f = f * f * (3.0 - 2.0 * f)  # smoothstep fade: C1 across cells
        i = i.astype(np.int64)
        x0 = (i[:, 0] & _MASK) << (2 * TABLE_BITS)
        y0 = (i[:, 1] & _MASK) << TABLE_BITS
        z0 = i[:, 2] & _MASK
        x1 = ((i[:, 0] + 1) & _MASK) << (2 * TABLE_BITS)
        y1 = ((i[:, 1] + 1) & _MASK) << TABLE_BITS
        z1 = (i[:, 2] + 1) & _MASK
        t = self.table
        fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
        c00 = t[x0 + y0 + z0] + fz * (t[x0 + y0 + z1] - t[x0 + y0 + z0])
        c01 = t[x0 + y1 + z0] + fz * (t[x0 + y1 + z1] - t[x0 + y1 + z0])
        c10 = t[x1 + y0 + z0] + fz * (t[x1 + y0 + z1] - t[x1 + y0 + z0])
        c11 = t[x1 + y1 + z0] + fz * (t[x1 + y1 + z1] - t[x1 + y1 + z0])
        c0 = c00 + fy * (c01 - c00)
        c1 = c10 + fy * (c11 - c10)
        return c0 + fx * (c1 - c0)

    def fbm(self, p: np.ndarray, octaves: int = 4, gain: float = 0.55,
            first_octave: int = 0) -> np.ndarray:
        """Fractal sum of ``octaves`` octaves (frequency x2 each), normalised to about [0, 1].

        The result is contrast-stretched so that its spread does not shrink with the number of
        octaves (a plain sum of many octaves tends to a flat grey).
        """
        p = np.asarray(p, np.float32)
        total = np.zeros(p.shape[0], np.float32)
        amp, norm, freq = 1.0, 0.0, 1.0
        for k in range(octaves):
            total += amp * (self.value(p * freq, first_octave + k) - 0.5)
            norm += amp * amp
            amp *= gain
            freq *= 2.0
        # the sum of independent octaves has std ~ 0.2 * sqrt(norm); rescale to std ~0.2
        return np.clip(0.5 + total / np.sqrt(norm), 0.0, 1.0)
