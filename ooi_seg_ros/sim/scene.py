"""A procedural scene: meshes with materials, the object of interest, lighting, ground truth."""

from __future__ import annotations

from dataclasses import dataclass, field
import numpy as np
import open3d as o3d

from ..core.types import TriMesh
from .materials import Lighting, Material
from .noise import NoiseField
from .shapes import vertex_normals


@dataclass
class Part:
    """One closed mesh of the scene with its material."""

    name: str
    vertices: np.ndarray  # [V, 3] float64
    triangles: np.ndarray  # [F, 3] int32
    material: str  # key into SimScene.materials
    ooi: bool = False  # part of the object of interest
    casts_shadow: bool = True  # occludes the light (walls/roofs of rooms do not)


@dataclass(frozen=True)
class Ring:
    """One drone orbit ring around the OOI centre."""

    elevation_deg: float  # angle above the horizontal, seen from the OOI centre
    distance: float  # distance to the OOI centre in units of the OOI bounding radius


@dataclass
class SimScene:
    """A scene ready to render, with exact ground truth.

    Build one with ``make_scene(name, seed)``. ``support_z`` is the height of the surface the
    OOI stands on (floor, table top, lawn); the OOI touches it.
    """

    name: str
    seed: int
    parts: list[Part]
    materials: dict[str, Material]
    lighting: Lighting
    support_z: float  # height of the surface the OOI rests on
    camera_bounds: tuple[np.ndarray, np.ndarray]  # (lo [3], hi [3]) the drone stays inside
    rings: tuple[Ring, ...]  # default orbit rings for this scene
    indoor: bool = False  # rays that hit nothing show a dim fill instead of sky
    description: str = ""
    _cache: dict = field(default_factory=dict, repr=False)

    # ---- merged geometry -------------------------------------------------------------------
    def _build(self) -> None:
        if "V" in self._cache:
            return
        names = sorted(self.materials)
        mat_index = {m: i for i, m in enumerate(names)}
        V, F, tmat, tooi, tpart, tcast = [], [], [], [], [], []
        n = 0
        for k, part in enumerate(self.parts):
            V.append(np.asarray(part.vertices, float))
            F.append(np.asarray(part.triangles, np.int64) + n)
            m = len(part.triangles)
            tmat.append(np.full(m, mat_index[part.material], np.int32))
            tooi.append(np.full(m, part.ooi))
            tpart.append(np.full(m, k, np.int32))
            tcast.append(np.full(m, part.casts_shadow))
            n += len(part.vertices)
        c = self._cache
        c["V"] = np.concatenate(V)
        c["F"] = np.concatenate(F).astype(np.int32)
        c["N"] = np.concatenate([vertex_normals(np.asarray(p.vertices, float),
                                                np.asarray(p.triangles, np.int64))
                                 for p in self.parts]).astype(np.float32)
        c["tri_material"] = np.concatenate(tmat)
        c["tri_ooi"] = np.concatenate(tooi)
        c["tri_part"] = np.concatenate(tpart)
        c["tri_cast"] = np.concatenate(tcast)
        c["material_names"] = names
        c["noise"] = NoiseField(self.seed)

    def _get(self, key: str):
        self._build()
        return self._cache[key]

    @staticmethod
    def _raycaster(V: np.ndarray, F: np.ndarray) -> o3d.t.geometry.RaycastingScene:
        rs = o3d.t.geometry.RaycastingScene()
        rs.add_triangles(o3d.core.Tensor(np.ascontiguousarray(V, np.float32)),
                         o3d.core.Tensor(np.ascontiguousarray(F, np.uint32)))
        return rs

    def raycaster(self, which: str = "all") -> o3d.t.geometry.RaycastingScene:
        """Open3D ray-casting scene of ``all`` geometry, the ``ooi`` or the ``casters``."""
        key = "rs_" + which
        if key not in self._cache:
            V, F = self._get("V"), self._get("F")
            if which == "all":
                sel = np.ones(len(F), bool)
            elif which == "ooi":
                sel = self._get("tri_ooi")
            elif which == "casters":
                sel = self._get("tri_cast")
            else:
                raise ValueError(f"unknown raycaster {which!r}; use all, ooi or casters")
            self._cache[key] = self._raycaster(V, F[sel])
        return self._cache[key]

    # ---- ground truth ------------------------------------------------------------------------
    def ooi_parts(self) -> list[Part]:
        return [p for p in self.parts if p.ooi]

    def ooi_mesh(self) -> TriMesh:
        """The OOI as one triangle mesh (its parts may overlap)."""
        V, F = self._get("V"), self._get("F")
        Fo = F[self._get("tri_ooi")]
        used, inv = np.unique(Fo, return_inverse=True)
        return TriMesh(V[used].copy(), inv.reshape(-1, 3).astype(np.int32))

    def background_mesh(self) -> TriMesh:
        """Everything that is not the OOI, as one triangle mesh."""
        V, F = self._get("V"), self._get("F")
        Fb = F[~self._get("tri_ooi")]
        used, inv = np.unique(Fb, return_inverse=True)
        return TriMesh(V[used].copy(), inv.reshape(-1, 3).astype(np.int32))

    def meshes(self) -> dict[str, TriMesh]:
        """Every part as its own mesh, by part name."""
        return {p.name: TriMesh(np.asarray(p.vertices, float), np.asarray(p.triangles, np.int32))
                for p in self.parts}

    @property
    def ooi_bbox(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box (lo [3], hi [3]) of the OOI."""
        if "ooi_bbox" not in self._cache:
            v = np.concatenate([p.vertices for p in self.ooi_parts()])
            self._cache["ooi_bbox"] = (v.min(0), v.max(0))
        return self._cache["ooi_bbox"]

    @property
    def ooi_center(self) -> np.ndarray:
        lo, hi = self.ooi_bbox
        return (lo + hi) / 2

    @property
    def ooi_diagonal(self) -> float:
        lo, hi = self.ooi_bbox
        return float(np.linalg.norm(hi - lo))

    @property
    def ooi_radius(self) -> float:
        """Radius of the sphere about ``ooi_center`` that holds the OOI."""
        if "ooi_radius" not in self._cache:
            v = np.concatenate([p.vertices for p in self.ooi_parts()])
            self._cache["ooi_radius"] = float(np.linalg.norm(v - self.ooi_center, axis=1).max())
        return self._cache["ooi_radius"]

    @property
    def scene_size(self) -> float:
        """Diagonal of the whole scene's bounding box (metres)."""
        V = self._get("V")
        return float(np.linalg.norm(V.max(0) - V.min(0)))

    def distance_to_surface(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance [N] from each point to the nearest scene surface (any part)."""
        return self._distance("all", points)

    def distance_to_ooi(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance [N] from each point to the OOI surface."""
        return self._distance("ooi", points)

    def _distance(self, which: str, points: np.ndarray) -> np.ndarray:
        pts = np.ascontiguousarray(np.asarray(points, float).reshape(-1, 3), np.float32)
        if len(pts) == 0:
            return np.zeros(0)
        d = self.raycaster(which).compute_distance(o3d.core.Tensor(pts)).numpy()
        return d.astype(np.float64)

    def sample_ooi_points(self, n: int = 20000, seed: int = 0) -> np.ndarray:
        """``n`` points [n, 3] uniformly on the OOI's outer surface.

        Area-weighted samples over the OOI triangles; samples that fall inside another OOI
        part (where parts overlap, e.g. a strut inside the fuselage) or on a face resting on
        the support (a pot's bottom) are not on the visible surface and are drawn again.
        """
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x0015]))
        parts = self.ooi_parts()
        areas = []
        for p in parts:
            t = p.vertices[p.triangles]
            areas.append(0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]),
                                              axis=1))
        part_area = np.array([a.sum() for a in areas])
        out: list[np.ndarray] = []
        have = 0
        for _ in range(20):
            m = int((n - have) * 1.3) + 16
            counts = rng.multinomial(m, part_area / part_area.sum())
            pts, owner = [], []
            for k, (p, a, c) in enumerate(zip(parts, areas, counts)):
                if c == 0:
                    continue
                tri = rng.choice(len(a), size=c, p=a / a.sum())
                r1, r2 = rng.random(c), rng.random(c)
                s = np.sqrt(r1)
                w0, w1, w2 = 1 - s, s * (1 - r2), s * r2
                t = p.vertices[p.triangles[tri]]
                pts.append(w0[:, None] * t[:, 0] + w1[:, None] * t[:, 1] + w2[:, None] * t[:, 2])
                owner.append(np.full(c, k))
            P = np.concatenate(pts)
            own = np.concatenate(owner)
            keep = ~self._inside_other_part(P, own, parts)
            # faces lying flat on the support (a pot's bottom) can never be seen
            keep &= np.abs(P[:, 2] - self.support_z) > 1e-7 * max(self.ooi_diagonal, 1e-3)
            out.append(P[keep])
            have += int(keep.sum())
            if have >= n:
                break
        allp = np.concatenate(out)
        return allp[:n]

    def _inside_other_part(self, P: np.ndarray, owner: np.ndarray,
                           parts: list[Part]) -> np.ndarray:
        inside = np.zeros(len(P), bool)
        for k, part in enumerate(parts):
            lo, hi = part.vertices.min(0), part.vertices.max(0)
            cand = np.nonzero((owner != k) & np.all((P > lo) & (P < hi), axis=1))[0]
            if len(cand) == 0:
                continue
            key = f"occ_{part.name}"
            if key not in self._cache:
                self._cache[key] = self._raycaster(part.vertices, part.triangles)
            occ = self._cache[key].compute_occupancy(
                o3d.core.Tensor(P[cand].astype(np.float32)), nsamples=3).numpy()
            inside[cand[occ > 0.5]] = True
        return inside

    def to_open3d(self, which: str = "all") -> o3d.geometry.TriangleMesh:
        """Legacy Open3D mesh of ``all`` / ``ooi`` / ``background`` geometry (for viewing)."""
        if which == "ooi":
            m = self.ooi_mesh()
            V, F = m.vertices, m.triangles
        elif which == "background":
            m = self.background_mesh()
            V, F = m.vertices, m.triangles
        else:
            V, F = self._get("V"), self._get("F")
        return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V),
                                         o3d.utility.Vector3iVector(F))

    def material_of_triangles(self) -> tuple[np.ndarray, list[str]]:
        """Per-triangle material index [F] and the material names it indexes."""
        return self._get("tri_material"), self._get("material_names")

    def noise(self) -> NoiseField:
        return self._get("noise")

    def summary(self) -> dict:
        """Scalar facts about the scene (for capture metadata)."""
        lo, hi = self.ooi_bbox
        return {"scene": self.name, "seed": int(self.seed), "scale": self.ooi_diagonal,
                "ooi_diagonal": self.ooi_diagonal, "ooi_radius": self.ooi_radius,
                "ooi_bbox_min": lo.tolist(), "ooi_bbox_max": hi.tolist(),
                "ooi_center": self.ooi_center.tolist(), "scene_size": self.scene_size,
                "support_z": float(self.support_z), "n_triangles": int(len(self._get("F")))}
