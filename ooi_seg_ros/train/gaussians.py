"""Gaussian splat model: parameters, initialisation from a point cloud, 3DGS PLY I/O.

The parameters are stored the way the reference 3DGS implementation stores them (log-scales,
quaternions w,x,y,z, logit-opacities, SH coefficients with the DC term separate), so that the
PLY written here opens in SuperSplat and other standard viewers without conversion.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch

from ..core.types import InputError

SH_C0 = 0.28209479177387814  # Y_0^0
MAX_SH_DEGREE = 3


def num_sh_rest(degree: int) -> int:
    """Number of non-DC SH coefficients per colour channel for ``degree`` (15 for degree 3)."""
    return (degree + 1) ** 2 - 1


def rgb_to_sh_dc(rgb: np.ndarray) -> np.ndarray:
    """Colour in [0, 1] -> DC SH coefficient (the renderer adds 0.5 after evaluating SH)."""
    return (rgb - 0.5) / SH_C0


@dataclass
class GaussianModel:
    """Trainable Gaussian parameters (all float32 torch tensors on one device).

    means [N, 3] world positions; log_scales [N, 3]; quats [N, 4] (w, x, y, z, unnormalised);
    logit_opacities [N]; sh_dc [N, 3]; sh_rest [N, 15, 3] (degree-3 capacity, coefficient-major
    then channel, the bands above ``sh_degree`` are kept at zero by the renderer ignoring them).
    """

    means: torch.Tensor
    log_scales: torch.Tensor
    quats: torch.Tensor
    logit_opacities: torch.Tensor
    sh_dc: torch.Tensor
    sh_rest: torch.Tensor
    sh_degree: int = 0  # active SH degree (raised during training)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    def params(self) -> dict[str, torch.Tensor]:
        """The trainable tensors by name (same names as the optimiser groups)."""
        return {"means": self.means, "log_scales": self.log_scales, "quats": self.quats,
                "logit_opacities": self.logit_opacities, "sh_dc": self.sh_dc,
                "sh_rest": self.sh_rest}

    def requires_grad_(self, flag: bool = True) -> "GaussianModel":
        for t in self.params().values():
            t.requires_grad_(flag)
        return self

    def detached(self) -> "GaussianModel":
        """A copy without autograd history (for snapshots and evaluation)."""
        p = {k: v.detach().clone() for k, v in self.params().items()}
        return GaussianModel(**p, sh_degree=self.sh_degree)

    @property
    def opacities(self) -> torch.Tensor:  # [N]
        return torch.sigmoid(self.logit_opacities)

    @property
    def scales(self) -> torch.Tensor:  # [N, 3]
        return torch.exp(self.log_scales)

    def to(self, device: Union[str, torch.device]) -> "GaussianModel":
        p = {k: v.to(device) for k, v in self.params().items()}
        return GaussianModel(**p, sh_degree=self.sh_degree)


def knn_mean_distance(xyz: np.ndarray, k: int = 3) -> np.ndarray:
    """Mean distance of every point to its ``k`` nearest neighbours (duplicates ignored)."""
    from scipy.spatial import cKDTree

    n = len(xyz)
    if n < 2:
        return np.full(n, 1e-2)
    kk = min(k + 1, n)
    d, _ = cKDTree(xyz).query(xyz, k=kk)
    d = np.asarray(d)[:, 1:]
    pos = np.where(d > 0, d, np.nan)
    out = np.nanmean(pos, axis=1) if pos.size else np.zeros(n)
    fallback = np.nanmedian(out) if np.isfinite(out).any() else 1e-2
    return np.where(np.isfinite(out), out, fallback)


def init_from_points(xyz: np.ndarray, rgb: Optional[np.ndarray] = None,
                     initial_opacity: float = 0.5, initial_scale_factor: float = 1.0,
                     device: Union[str, torch.device] = "cpu") -> GaussianModel:
    """Isotropic Gaussians at the points of a cloud (paper 4.6: the OOI cloud).

    Scale = mean distance to the 3 nearest neighbours (so the initial splats just touch),
    colour from ``rgb`` (uint8 or [0, 1] floats; grey if None), opacity ``initial_opacity``.
    """
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    if len(xyz) == 0 or not np.isfinite(xyz).all():
        raise InputError("the initial point cloud is empty or has non-finite points; "
                         "segment the OOI first (ooi-seg segment) or pass a cloud with points")
    n = len(xyz)
    if rgb is None:
        col = np.full((n, 3), 0.5)
    else:
        col = np.asarray(rgb, dtype=np.float64).reshape(n, 3)
        if col.max(initial=0.0) > 1.0:
            col = col / 255.0
    dist = knn_mean_distance(xyz) * initial_scale_factor
    dist = np.clip(dist, 1e-7, None)
    f32 = dict(dtype=torch.float32, device=device)
    quats = torch.zeros((n, 4), **f32)
    quats[:, 0] = 1.0
    p = float(np.clip(initial_opacity, 1e-4, 1 - 1e-4))
    return GaussianModel(
        means=torch.tensor(xyz, **f32),
        log_scales=torch.tensor(np.log(dist)[:, None].repeat(3, 1), **f32),
        quats=quats,
        logit_opacities=torch.full((n,), float(np.log(p / (1 - p))), **f32),
        sh_dc=torch.tensor(rgb_to_sh_dc(col), **f32),
        sh_rest=torch.zeros((n, num_sh_rest(MAX_SH_DEGREE), 3), **f32),
    )


PLY_FIELDS = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
              + [f"f_rest_{i}" for i in range(45)]
              + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def to_ply_array(model: GaussianModel) -> np.ndarray:
    """[N, 62] float32 rows in PLY_FIELDS order (f_rest channel-major like the reference)."""
    m = model.detached().to("cpu")
    n = len(m)
    rest = m.sh_rest.transpose(1, 2).reshape(n, -1)  # [N, 3*15]: all R, then G, then B
    cols = [m.means, torch.zeros((n, 3)), m.sh_dc, rest, m.logit_opacities[:, None],
            m.log_scales, m.quats]
    return torch.cat(cols, dim=1).numpy().astype(np.float32)


def from_ply_array(arr: np.ndarray, sh_degree: int = MAX_SH_DEGREE) -> GaussianModel:
    """Inverse of ``to_ply_array``."""
    arr = np.asarray(arr, dtype=np.float32)
    t = torch.from_numpy(arr.copy())
    n = t.shape[0]
    return GaussianModel(means=t[:, 0:3].clone(), log_scales=t[:, 55:58].clone(),
                         quats=t[:, 58:62].clone(), logit_opacities=t[:, 54].clone(),
                         sh_dc=t[:, 6:9].clone(),
                         sh_rest=t[:, 9:54].reshape(n, 3, 15).transpose(1, 2).contiguous(),
                         sh_degree=sh_degree)


def save_ply(model: GaussianModel, path: Union[str, Path]) -> None:
    """Write the standard 3DGS binary little-endian PLY (SuperSplat / reference layout)."""
    arr = to_ply_array(model)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {arr.shape[0]}"]
    header += [f"property float {name}" for name in PLY_FIELDS]
    header += ["end_header"]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(arr.astype("<f4").tobytes())


def read_ply_header(path: Union[str, Path]) -> tuple[list[str], int, int, str]:
    """(property names, vertex count, byte offset of the data, format) of a PLY file."""
    names: list[str] = []
    count, fmt = -1, ""
    with open(path, "rb") as f:
        first = f.readline().strip()
        if first != b"ply":
            raise InputError(f"{path} is not a PLY file (no 'ply' magic line)")
        while True:
            line = f.readline()
            if not line:
                raise InputError(f"{path}: PLY header has no end_header line")
            tok = line.decode("ascii", "replace").split()
            if not tok:
                continue
            if tok[0] == "format":
                fmt = tok[1]
            elif tok[0] == "element" and tok[1] == "vertex":
                count = int(tok[2])
            elif tok[0] == "property" and count >= 0:
                if tok[1] != "float":
                    raise InputError(f"{path}: property {tok[-1]} is {tok[1]}, expected float")
                names.append(tok[2])
            elif tok[0] == "end_header":
                return names, count, f.tell(), fmt


def load_ply(path: Union[str, Path]) -> GaussianModel:
    """Read a 3DGS PLY (any property order; missing f_rest bands are zero)."""
    names, count, offset, fmt = read_ply_header(path)
    if fmt != "binary_little_endian":
        raise InputError(f"{path}: only binary_little_endian 3DGS PLY files are supported")
    missing = [k for k in ("x", "y", "z", "f_dc_0", "opacity", "scale_0", "rot_0")
               if k not in names]
    if missing:
        raise InputError(f"{path} is not a Gaussian splat PLY (missing {', '.join(missing)})")
    with open(path, "rb") as f:
        f.seek(offset)
        raw = np.frombuffer(f.read(count * 4 * len(names)), dtype="<f4")
    if raw.size != count * len(names):
        raise InputError(f"{path} is truncated ({raw.size} of {count * len(names)} floats)")
    raw = raw.reshape(count, len(names))
    out = np.zeros((count, len(PLY_FIELDS)), dtype=np.float32)
    for j, name in enumerate(PLY_FIELDS):
        if name in names:
            out[:, j] = raw[:, names.index(name)]
    n_rest = sum(1 for n in names if n.startswith("f_rest_"))
    degree = int(round(np.sqrt(n_rest // 3 + 1))) - 1 if n_rest else 0
    if n_rest and n_rest != 45:  # fewer bands: reference layout is channel-major per band count
        k = n_rest // 3
        rest = np.stack([raw[:, names.index(f"f_rest_{i}")] for i in range(n_rest)], 1)
        full = np.zeros((count, 3, 15), dtype=np.float32)
        full[:, :, :k] = rest.reshape(count, 3, k)
        out[:, 9:54] = full.reshape(count, 45)
    return from_ply_array(out, sh_degree=max(degree, 0))
