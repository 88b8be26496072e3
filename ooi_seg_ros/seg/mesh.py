"""Stage 4.4: surface mesh of the OOI cloud.

Normals are estimated with a hybrid KD-tree search whose radius is derived from the cloud's
spacing, then oriented towards the cameras that observed each point (the mean direction to
the observing cameras; the cloud's centroid is used for points without observations). The
paper's mesh is a screened Poisson reconstruction at depth 9 with the lowest-density vertices
trimmed; ball pivoting (radii from the spacing) is the alternative.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.types import SfmCloud, TriMesh
from .density import spacing


@dataclass
class MeshConfig:
    """Options of the meshing stage."""

    method: str = "poisson"  # "poisson" | "ball_pivoting" | "none"
    normal_radius_scale: float = 4.0  # normal search radius in cloud spacings
    normal_max_nn: int = 30  # max neighbours for the normal fit
    poisson_depth: int = 9  # octree depth of the Poisson reconstruction
    trim_quantile: float = 0.1  # drop Poisson vertices below this density quantile
    bpa_radii: tuple = (1.0, 2.0, 4.0)  # ball-pivoting radii in cloud spacings


def oriented_normals(cloud: SfmCloud, radius: float, max_nn: int) -> np.ndarray:
    """Unit normals [N,3] oriented towards the cameras that observed each point."""
    import open3d as o3d
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud.xyz))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn))
    nrm = np.asarray(pc.normals).copy()
    centers = np.array([v.pose.t for v in cloud.views]) if cloud.views else np.zeros((0, 3))
    to_cam = cloud.xyz.mean(axis=0) - cloud.xyz  # fallback: away from the centroid, flipped
    to_cam = -to_cam
    lens = cloud.track_lengths()
    if len(centers) and len(cloud.obs_view):
        pid = np.repeat(np.arange(len(cloud)), lens)
        dirs = centers[cloud.obs_view] - cloud.xyz[pid]
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True) + 1e-12
        acc = np.zeros_like(cloud.xyz)
        np.add.at(acc, pid, dirs)
        has = lens > 0
        to_cam[has] = acc[has]
    flip = np.einsum("ij,ij->i", nrm, to_cam) < 0
    nrm[flip] *= -1
    return nrm


def build_mesh(cloud: SfmCloud, cfg: MeshConfig) -> tuple[TriMesh, dict]:
    """Mesh of the OOI cloud (empty TriMesh for method "none" or too few points)."""
    import open3d as o3d
    empty = TriMesh(np.zeros((0, 3)), np.zeros((0, 3), np.int32))
    if cfg.method == "none" or len(cloud) < 10:
        return empty, {"method": cfg.method, "skipped": len(cloud) < 10}
    s = spacing(cloud.xyz)
    nrm = oriented_normals(cloud, cfg.normal_radius_scale * s, cfg.normal_max_nn)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud.xyz))
    pc.normals = o3d.utility.Vector3dVector(nrm)
    params: dict = {"method": cfg.method, "spacing": s}
    if cfg.method == "poisson":
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            # one thread: Open3D's multi-threaded Poisson gives a different mesh on every
            # call (isl-org/Open3D#2117; measured here: 4 calls, 4 meshes), which made the
            # masks of one input differ between runs; one thread was as fast on this box
            m, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
                pc, depth=int(cfg.poisson_depth), n_threads=1)
        dens = np.asarray(dens)
        if cfg.trim_quantile > 0 and len(dens):
            cut = np.quantile(dens, cfg.trim_quantile)
            m.remove_vertices_by_mask(dens < cut)
            params["trim_density"] = float(cut)
    elif cfg.method == "ball_pivoting":
        radii = o3d.utility.DoubleVector([r * s for r in cfg.bpa_radii])
        m = o3d.geometry.TriangleMesh.create_from_point_cloud_ball_pivoting(pc, radii)
    else:
        raise ValueError(f"mesh.method={cfg.method!r}; use poisson, ball_pivoting or none")
    mesh = TriMesh(np.asarray(m.vertices, float), np.asarray(m.triangles, np.int32))
    params["vertices"] = int(len(mesh.vertices))
    params["triangles"] = int(len(mesh.triangles))
    return mesh, params
