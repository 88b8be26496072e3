"""The procedural scenes: an object of interest on its support, with background and clutter.

Sizes differ by orders of magnitude on purpose (an aircraft of ~20 m in a 90 m hangar, a
potted plant of ~0.3 m on a table, a bicycle of ~1.8 m on a lawn, a toy car of ~0.2 m among
tools on a workbench) so that scale-dependent parameters of later stages are exercised. The
plant also stands on a cloth-covered stool in a room (``stool``), seen from farther away: a
support that itself stands on the floor, with textured sides hanging below its top.
Clutter placement, plant leaves and bushes are random but fixed by the scene seed.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .materials import Decal, Lighting, Material, rgb255
from .scene import Part, Ring, SimScene
from .shapes import (Mesh, blob, box, cylinder, hexahedron, lathe, rot_y, rot_z, sphere, torus,
                     transform)


class _Builder:
    """Collects parts and materials while a scene is being built."""

    def __init__(self) -> None:
        self.parts: list[Part] = []
        self.materials: dict[str, Material] = {}

    def mat(self, name: str, material: Material) -> str:
        self.materials[name] = material
        return name

    def add(self, name: str, mesh: Mesh, material: str, ooi: bool = False,
            casts_shadow: bool = True) -> None:
        v, f = mesh
        k = sum(1 for p in self.parts if p.name == name or p.name.startswith(name + "_"))
        uname = name if k == 0 else f"{name}_{k}"
        self.parts.append(Part(uname, np.asarray(v, float), np.asarray(f, np.int32), material,
                               ooi, casts_shadow))


def _rng(seed: int, name: str) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), sum(map(ord, name))]))


def _wheel(center: np.ndarray, radius: float, width: float, axis: np.ndarray,
           segments: int = 24) -> Mesh:
    """A solid wheel (cylinder) whose lowest rim vertex is exactly ``radius`` below center."""
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    return cylinder(center - axis * width / 2, center + axis * width / 2, radius, segments)


def _scatter(rng: np.random.Generator, n: int, r_min: float, r_max: float,
             keep_out: Callable[[float, float], bool], min_sep: float,
             center: tuple[float, float] = (0.0, 0.0),
             bounds: tuple[float, float, float, float] | None = None) -> list[tuple]:
    """``n`` (x, y, yaw) positions in an annulus, apart from each other and keep-out zones."""
    out: list[tuple] = []
    for _ in range(n * 60):
        if len(out) >= n:
            break
        r = np.sqrt(rng.uniform(r_min ** 2, r_max ** 2))
        a = rng.uniform(0, 2 * np.pi)
        x, y = center[0] + r * np.cos(a), center[1] + r * np.sin(a)
        if bounds is not None and not (bounds[0] < x < bounds[1] and bounds[2] < y < bounds[3]):
            continue
        if keep_out(x, y) or any(np.hypot(x - q[0], y - q[1]) < min_sep for q in out):
            continue
        out.append((x, y, rng.uniform(0, 2 * np.pi)))
    return out


# ------------------------------------------------------------------------------------------
# aircraft in a hangar
# ------------------------------------------------------------------------------------------
def _aircraft(b: _Builder, seed: int) -> None:
    """A business jet (~20 m) standing on its landing gear at z = 0, nose towards +x."""
    white = b.mat("paint_white", Material(
        (rgb255(166, 172, 180), rgb255(242, 242, 244)), scale=1.5, octaves=6, contrast=1.8,
        spot_color=rgb255(128, 124, 116), spot_frac=0.08, spot_scale=0.8,
        grid=(1.1, 0.03, 0.3), seed=1,
        decals=(Decal((-10, -3, 1.95), (8.6, 3, 2.3), rgb255(24, 46, 110)),  # cheat line
                Decal((-10, -3, 2.3), (8.6, 3, 2.4), rgb255(190, 30, 40)),
                *[Decal((x, -3, 2.5), (x + 0.32, 3, 2.78), rgb255(30, 34, 44), 0.1)
                  for x in np.arange(-3.0, 5.0, 0.95)],  # cabin windows
                Decal((7.6, -3, 2.55), (8.7, 3, 3.2), rgb255(20, 24, 32), 0.1),  # windscreen
                Decal((-2.8, -3, 1.2), (-1.0, 3, 1.6), rgb255(60, 66, 80), 0.2))))
    wing = b.mat("paint_wing", Material(
        (rgb255(140, 146, 156), rgb255(225, 228, 232)), scale=1.2, octaves=6, contrast=1.8,
        spot_color=rgb255(100, 102, 106), spot_frac=0.08, spot_scale=0.6,
        grid=(0.9, 0.03, 0.25), seed=2,
        decals=(Decal((-6, -9, 1.0), (0, -8.3, 3.0), rgb255(190, 30, 40)),
                Decal((-6, 8.3, 1.0), (0, 9, 3.0), rgb255(190, 30, 40)))))
    tail = b.mat("paint_tail", Material(
        (rgb255(24, 46, 110), rgb255(60, 90, 170)), scale=1.2, octaves=5, contrast=1.4,
        stripes=((0.3, 0.0, 0.95), 0.9, 0.35, rgb255(235, 235, 240)), seed=3))
    metal = b.mat("nacelle", Material(
        (rgb255(110, 114, 120), rgb255(200, 204, 210)), scale=0.9, octaves=5, contrast=1.5,
        spot_color=rgb255(50, 50, 54), spot_frac=0.08, grid=(0.6, 0.03, 0.5), seed=4))
    rubber = b.mat("tyre", Material(
        (rgb255(14, 14, 16), rgb255(60, 60, 62)), scale=0.25, octaves=3, contrast=1.3, seed=5))
    gear = b.mat("gear", Material(
        (rgb255(120, 124, 130), rgb255(210, 212, 215)), scale=0.3, octaves=3, seed=6))

    fus = lathe([(0.0, -10.0), (0.3, -9.9), (0.55, -8.5), (0.85, -6.5), (1.1, -4.0),
                 (1.1, 5.5), (1.05, 7.0), (0.9, 8.2), (0.65, 9.1), (0.35, 9.7), (0.0, 10.0)], 40)
    b.add("fuselage", transform(fus, rot_y(np.pi / 2), (0, 0, 2.2)), white, ooi=True)
    for s in (1, -1):
        # low swept wing with dihedral: root inside the fuselage, tip at |y| = 9.5
        z0, z1 = 1.55, 1.95
        c = np.array([[1.6, 0, z0 - 0.18], [-2.6, 0, z0 - 0.18], [-4.1, 9.5 * s, z1 - 0.06],
                      [-2.6, 9.5 * s, z1 - 0.06],
                      [1.6, 0, z0 + 0.18], [-2.6, 0, z0 + 0.18], [-4.1, 9.5 * s, z1 + 0.06],
                      [-2.6, 9.5 * s, z1 + 0.06]])
        b.add("wing", hexahedron(c), wing, ooi=True)
        # winglet
        c = np.array([[-2.7, 9.42 * s, z1], [-4.0, 9.42 * s, z1], [-4.6, 9.52 * s, z1 + 1.3],
                      [-3.9, 9.52 * s, z1 + 1.3],
                      [-2.7, 9.58 * s, z1], [-4.0, 9.58 * s, z1], [-4.6, 9.66 * s, z1 + 1.3],
                      [-3.9, 9.66 * s, z1 + 1.3]])
        b.add("winglet", hexahedron(c), tail, ooi=True)
        # horizontal stabiliser on top of the fin (T-tail)
        c = np.array([[-8.9, 0, 5.75], [-10.9, 0, 5.75], [-11.4, 3.7 * s, 5.95],
                      [-10.4, 3.7 * s, 5.95],
                      [-8.9, 0, 5.95], [-10.9, 0, 5.95], [-11.4, 3.7 * s, 6.05],
                      [-10.4, 3.7 * s, 6.05]])
        b.add("stabiliser", hexahedron(c), tail, ooi=True)
        # rear-mounted engine on a pylon
        nac = lathe([(0.0, 0.0), (0.38, 0.02), (0.55, 0.3), (0.56, 2.2), (0.42, 3.1),
                     (0.28, 3.3), (0.0, 3.32)], 28)
        b.add("engine", transform(nac, rot_y(-np.pi / 2), (-3.0, 1.75 * s, 2.95)), metal,
              ooi=True)
        c = np.array([[-4.0, 0.3 * s, 2.75], [-5.6, 0.3 * s, 2.75], [-5.6, 1.4 * s, 2.85],
                      [-4.2, 1.4 * s, 2.85],
                      [-4.0, 0.3 * s, 3.0], [-5.6, 0.3 * s, 3.0], [-5.6, 1.4 * s, 3.05],
                      [-4.2, 1.4 * s, 3.05]])
        b.add("pylon", hexahedron(c), white, ooi=True)
        # main gear: strut from the wing root down to a wheel pair touching the ground
        y = 1.9 * s
        b.add("main_strut", cylinder((-1.3, y, 1.45), (-1.3, y, 0.42), 0.09, 12), gear, ooi=True)
        b.add("main_strut_brace", cylinder((-1.3, y, 0.9), (-0.3, y * 0.7, 1.45), 0.045, 10),
              gear, ooi=True)
        for dy in (-0.17, 0.17):
            b.add("main_wheel", _wheel(np.array([-1.3, y + dy, 0.42]), 0.42, 0.22,
                                       np.array([0, 1.0, 0]), 28), rubber, ooi=True)
    # vertical fin: swept, from the tail cone up to the T-tail
    c = np.array([[-6.4, -0.16, 2.5], [-9.6, -0.16, 2.5], [-10.8, -0.09, 6.0], [-9.1, -0.09, 6.0],
                  [-6.4, 0.16, 2.5], [-9.6, 0.16, 2.5], [-10.8, 0.09, 6.0], [-9.1, 0.09, 6.0]])
    b.add("fin", hexahedron(c), tail, ooi=True)
    # nose gear
    b.add("nose_strut", cylinder((7.0, 0, 1.4), (7.0, 0, 0.3), 0.07, 12), gear, ooi=True)
    for dy in (-0.13, 0.13):
        b.add("nose_wheel", _wheel(np.array([7.0, dy, 0.3]), 0.3, 0.16, np.array([0, 1.0, 0]),
                                   24), rubber, ooi=True)
    # antennas / probes: thin structures with almost no texture
    b.add("antenna", cylinder((2.0, 0, 3.25), (1.6, 0, 3.75), 0.03, 8), gear, ooi=True)
    b.add("pitot", cylinder((8.3, 0.75, 2.3), (8.9, 0.9, 2.3), 0.02, 8), gear, ooi=True)


def _hangar(b: _Builder, seed: int) -> None:
    """A hangar 90 x 80 x 24 m: painted concrete floor, corrugated walls, doors, roof trusses,
    and the clutter of a maintenance floor (tool carts, barrels, crates, stairs, a tug)."""
    rng = _rng(seed, "hangar")
    X, Y, Z = 45.0, 40.0, 24.0
    floor = b.mat("hangar_floor", Material(
        (rgb255(104, 104, 100), rgb255(178, 176, 170)), scale=4.0, octaves=7, contrast=1.5,
        spot_color=rgb255(70, 68, 64), spot_frac=0.05, spot_scale=2.0, grain=0.12,
        grid=(6.0, 0.12, 0.35), seed=10,
        decals=(Decal((-45, -0.12, -1), (45, 0.12, 0.01), rgb255(222, 180, 30)),  # taxi line
                Decal((-14, -12.2, -1), (14, -11.9, 0.01), rgb255(230, 230, 225)),
                Decal((-14, 11.9, -1), (14, 12.2, 0.01), rgb255(230, 230, 225)),
                Decal((-14.2, -12.2, -1), (-13.9, 12.2, 0.01), rgb255(230, 230, 225)),
                Decal((13.9, -12.2, -1), (14.2, 12.2, 0.01), rgb255(230, 230, 225)),
                Decal((-30, -30.3, -1), (30, -29.7, 0.01), rgb255(200, 40, 40)),
                Decal((-30, 29.7, -1), (30, 30.3, 0.01), rgb255(200, 40, 40)),
                Decal((20, -6, -1), (21.2, 6, 0.01), rgb255(222, 180, 30)))))
    wall = b.mat("hangar_wall", Material(
        (rgb255(120, 128, 132), rgb255(196, 202, 204)), scale=6.0, octaves=6, contrast=1.4,
        spot_color=rgb255(120, 104, 88), spot_frac=0.04, spot_scale=2.0,
        stripes=((0.7071, 0.7071, 0.0), 0.8, 0.3, rgb255(100, 106, 112)), seed=11,
        decals=(Decal((-50, -50, -1), (50, 50, 1.6), rgb255(60, 64, 70), 0.35),
                *[Decal((-50, -50, 15.0 + 0 * k), (50, 50, 17.0), rgb255(170, 200, 225), 0.15)
                  for k in range(1)])))
    roof = b.mat("hangar_roof", Material(
        (rgb255(70, 72, 76), rgb255(140, 142, 146)), scale=8.0, octaves=5, contrast=1.3,
        grid=(4.0, 0.2, 0.5), seed=12))
    steel = b.mat("truss", Material(
        (rgb255(150, 60, 30), rgb255(210, 110, 60)), scale=2.0, octaves=4, seed=13))
    door = b.mat("door", Material(
        (rgb255(60, 80, 110), rgb255(120, 140, 170)), scale=3.0, octaves=6, contrast=1.4,
        grid=(3.0, 0.12, 0.5), spot_color=rgb255(40, 44, 50), spot_frac=0.06, seed=14))
    hazard = b.mat("hazard", Material(
        (rgb255(210, 170, 20), rgb255(250, 210, 40)), scale=1.0, octaves=3,
        stripes=((0.0, 0.7071, 0.7071), 1.0, 0.5, rgb255(20, 20, 20)), seed=15))
    b.add("floor", box((2 * X, 2 * Y, 0.2), (0, 0, -0.1)), floor, casts_shadow=False)
    for sx in (-1, 1):
        b.add("wall_x", box((0.4, 2 * Y, Z), (sx * (X + 0.2), 0, Z / 2)), wall,
              casts_shadow=False)
    for sy in (-1, 1):
        b.add("wall_y", box((2 * X, 0.4, Z), (0, sy * (Y + 0.2), Z / 2)), wall,
              casts_shadow=False)
    b.add("roof", box((2 * X, 2 * Y, 0.5), (0, 0, Z + 0.25)), roof, casts_shadow=False)
    for x in np.arange(-X + 7.5, X, 7.5):
        b.add("truss", box((0.5, 2 * Y, 1.0), (x, 0, Z - 1.5)), steel, casts_shadow=False)
        for y in np.arange(-Y + 5, Y, 10.0):
            b.add("truss_diag", box((0.25, 0.25, 1.5), (x, y, Z - 0.5)), steel,
                  casts_shadow=False)
    for y in (-20.0, 0.0, 20.0):
        b.add("purlin", box((2 * X, 0.35, 0.6), (0, y, Z - 0.3)), steel, casts_shadow=False)
    # sliding doors on the wall in front of the nose, with hazard stripes at the bottom
    for k, y in enumerate(np.arange(-33.0, 34.0, 13.2)):
        b.add("door", box((0.5, 12.8, 18.0), (X - 0.3, y, 9.0)), door, casts_shadow=False)
        b.add("door_hazard", box((0.55, 12.8, 0.8), (X - 0.32, y, 0.4)), hazard,
              casts_shadow=False)

    # clutter on the floor, kept out of the aircraft's footprint
    def keep_out(x: float, y: float) -> bool:
        return abs(x) < 13.5 and abs(y) < 12.0

    cart = b.mat("cart_red", Material(
        (rgb255(150, 20, 24), rgb255(220, 50, 50)), scale=0.6, octaves=4, contrast=1.3,
        stripes=((0.0, 0.0, 1.0), 0.16, 0.12, rgb255(40, 40, 44)), seed=16))
    barrel_b = b.mat("barrel_blue", Material(
        (rgb255(20, 60, 130), rgb255(60, 110, 190)), scale=0.5, octaves=4, contrast=1.4,
        stripes=((0.0, 0.0, 1.0), 0.3, 0.12, rgb255(30, 40, 60)),
        spot_color=rgb255(140, 90, 50), spot_frac=0.15, seed=17))
    barrel_y = b.mat("barrel_yellow", Material(
        (rgb255(170, 130, 10), rgb255(240, 200, 40)), scale=0.5, octaves=4, contrast=1.4,
        stripes=((0.0, 0.0, 1.0), 0.3, 0.12, rgb255(60, 50, 20)),
        spot_color=rgb255(120, 80, 40), spot_frac=0.15, seed=18))
    wood = b.mat("crate_wood", Material(
        (rgb255(120, 84, 46), rgb255(200, 156, 100)), scale=0.8, octaves=5, contrast=1.5,
        stripes=((0.0, 0.0, 1.0), 0.18, 0.1, rgb255(70, 48, 28)), seed=19))
    grey = b.mat("equipment", Material(
        (rgb255(70, 80, 70), rgb255(140, 160, 140)), scale=1.0, octaves=5, contrast=1.4,
        spot_color=rgb255(220, 200, 60), spot_frac=0.1, grid=(0.5, 0.03, 0.5), seed=20))
    tyre = "tyre"
    spots = _scatter(rng, 34, 15.0, 38.0, keep_out, 2.6,
                     bounds=(-X + 1.5, X - 3, -Y + 1.5, Y - 1.5))
    for k, (x, y, yaw) in enumerate(spots):
        kind = k % 6
        R = rot_z(yaw)
        if kind == 0:  # tool cart on wheels
            b.add("tool_cart", box((1.1, 0.6, 0.85), (x, y, 0.55), R), cart)
            for dx, dy in ((-0.45, -0.22), (0.45, -0.22), (-0.45, 0.22), (0.45, 0.22)):
                c = np.array([x, y, 0.0]) + R @ np.array([dx, dy, 0.0])
                b.add("cart_wheel", _wheel(c + [0, 0, 0.06], 0.06, 0.04, R @ [0, 1.0, 0], 12),
                      tyre)
        elif kind == 1:  # barrels
            for j in range(int(rng.integers(2, 5))):
                c = np.array([x, y, 0]) + R @ np.array([0.65 * (j % 2), 0.65 * (j // 2), 0])
                b.add("barrel", cylinder(c, c + [0, 0, 0.9], 0.29, 20),
                      barrel_b if (j + k) % 2 else barrel_y)
        elif kind == 2:  # stacked crates
            s = rng.uniform(0.8, 1.4)
            b.add("crate", box((s, s, s), (x, y, s / 2), R), wood)
            if rng.random() < 0.6:
                s2 = s * 0.7
                b.add("crate", box((s2, s2, s2), (x, y, s + s2 / 2), rot_z(yaw + 0.4)), wood)
        elif kind == 3:  # maintenance stairs: a stepped platform on a frame
            for j in range(5):
                b.add("stairs", box((0.5, 1.0, 0.4 * (j + 1)), (x, y, 0.2 * (j + 1)) + R @
                                    np.array([0.5 * j, 0, 0]), R), grey)
        elif kind == 4:  # ground power unit / equipment box on wheels
            b.add("gpu_unit", box((2.2, 1.2, 1.3), (x, y, 0.85), R), grey)
            for dx in (-0.8, 0.8):
                for dy in (-0.55, 0.55):
                    c = np.array([x, y, 0]) + R @ np.array([dx, dy, 0])
                    b.add("gpu_wheel", _wheel(c + [0, 0, 0.2], 0.2, 0.12, R @ [0, 1.0, 0], 16),
                          tyre)
        else:  # traffic cones and a toolbox
            for j in range(3):
                c = np.array([x, y, 0]) + R @ np.array([0.9 * j, 0, 0])
                b.add("cone", cylinder(c, c + [0, 0, 0.7], 0.18, 16, radius1=0.03), hazard)
            b.add("toolbox", box((0.6, 0.3, 0.3), (x, y + 0.8, 0.15), R), cart)
    # a workbench along the back wall
    b.add("workbench", box((8.0, 1.0, 0.9), (-X + 0.7, 10.0, 0.45), rot_z(np.pi / 2)), wood)
    b.add("shelf", box((10.0, 0.8, 3.0), (-10.0, Y - 0.5, 1.5)), grey)


def make_aircraft(seed: int) -> SimScene:
    b = _Builder()
    _aircraft(b, seed)
    _hangar(b, seed)
    return SimScene(
        "aircraft", seed, b.parts, b.materials,
        Lighting(direction=(0.25, 0.35, 1.0), ambient=0.44, diffuse=0.56, shadow=0.55),
        support_z=0.0,
        camera_bounds=(np.array([-43.0, -38.0, 1.0]), np.array([43.0, 38.0, 22.0])),
        rings=(Ring(12.0, 2.0), Ring(26.0, 1.8), Ring(42.0, 1.6)), indoor=True,
        description="business jet on its landing gear on a painted hangar floor, with doors, "
                    "roof trusses and maintenance clutter")


# ------------------------------------------------------------------------------------------
# potted plant on a table in a room
# ------------------------------------------------------------------------------------------
def _room(b: _Builder, rng: np.random.Generator, X: float, Y: float, Z: float,
          wall_color: tuple) -> None:
    """A room with plank floor, painted walls, a window, pictures, ceiling, bookshelf, lamp."""
    floor = b.mat("planks", Material(
        (rgb255(110, 70, 40), rgb255(190, 140, 90)), scale=0.4, octaves=6, contrast=1.8,
        grain=0.3, stripes=((0.0, 1.0, 0.0), 0.16, 0.05, rgb255(50, 30, 18)), seed=30))
    wall = b.mat("plaster", Material(
        (tuple(c * 0.75 for c in wall_color), wall_color), scale=0.5, octaves=6, contrast=1.6,
        grain=0.2,
        spot_color=tuple(c * 0.85 for c in wall_color), spot_frac=0.03, seed=31,
        decals=(Decal((-9, -9, -1), (9, 9, 0.1), rgb255(240, 240, 236), 0.1),)))
    ceiling = b.mat("ceiling", Material(
        (rgb255(200, 200, 196), rgb255(236, 236, 232)), scale=0.8, octaves=4,
        grid=(0.6, 0.012, 0.3), seed=32))
    window = b.mat("window", Material(
        (rgb255(120, 160, 200), rgb255(200, 220, 240)), scale=0.6, octaves=5, contrast=1.5,
        grid=(0.45, 0.03, 0.8), seed=33))
    b.add("floor", box((2 * X, 2 * Y, 0.1), (0, 0, -0.05)), floor, casts_shadow=False)
    b.add("ceiling", box((2 * X, 2 * Y, 0.1), (0, 0, Z + 0.05)), ceiling, casts_shadow=False)
    for s in (-1, 1):
        b.add("wall_x", box((0.1, 2 * Y, Z), (s * (X + 0.05), 0, Z / 2)), wall,
              casts_shadow=False)
        b.add("wall_y", box((2 * X, 0.1, Z), (0, s * (Y + 0.05), Z / 2)), wall,
              casts_shadow=False)
    b.add("window", box((0.04, 1.4, 1.2), (X - 0.01, 0.3, 1.5)), window, casts_shadow=False)
    # pictures on the walls: high-contrast textured frames
    for k, (x, y, w, h) in enumerate([(-1.0, Y, 0.8, 0.6), (1.2, Y, 0.5, 0.7),
                                      (-X, -0.8, 0.9, 0.6), (0.6, -Y, 1.0, 0.7)]):
        m = b.mat(f"picture{k}", Material(
            (tuple(rng.uniform(0.05, 0.4, 3)), tuple(rng.uniform(0.6, 1.0, 3))), scale=0.25,
            octaves=5, contrast=2.2, spot_color=tuple(rng.uniform(0, 1, 3)), spot_frac=0.2,
            seed=40 + k))
        sx = 0.03 if abs(x) == X else w
        sy = 0.03 if abs(y) == Y else w
        cx = x - np.sign(x) * 0.02 if abs(x) == X else x
        cy = y - np.sign(y) * 0.02 if abs(y) == Y else y
        b.add("picture", box((sx, sy, h), (cx, cy, 1.55)), m, casts_shadow=False)
    # bookshelf with books of random colours along the -x wall
    shelf = b.mat("shelf_wood", Material(
        (rgb255(80, 50, 30), rgb255(150, 100, 60)), scale=0.3, octaves=5, contrast=1.4,
        stripes=((0.0, 0.0, 1.0), 0.05, 0.2, rgb255(60, 36, 20)), seed=34))
    sx0 = -X + 0.2
    b.add("shelf_side", box((0.36, 0.03, 1.9), (sx0, 0.9, 0.95)), shelf)
    b.add("shelf_side", box((0.36, 0.03, 1.9), (sx0, 1.85, 0.95)), shelf)
    for z in (0.02, 0.45, 0.9, 1.35, 1.88):
        b.add("shelf_board", box((0.36, 0.98, 0.03), (sx0, 1.375, z)), shelf)
        if z > 1.8:
            continue
        y = 0.93
        while y < 1.8:
            w = rng.uniform(0.025, 0.06)
            hgt = rng.uniform(0.25, 0.4)
            if y + w > 1.82:
                break
            m = b.mat(f"book{int(rng.integers(0, 6))}", Material(
                (tuple(rng.uniform(0.05, 0.5, 3)), tuple(rng.uniform(0.4, 0.9, 3))),
                scale=0.08, octaves=3, contrast=1.5,
                stripes=((0.0, 0.0, 1.0), 0.12, 0.15, rgb255(220, 200, 120)), seed=50))
            b.add("book", box((0.24, w, hgt), (sx0 + 0.04, y + w / 2, z + 0.015 + hgt / 2)), m)
            y += w + 0.003
    # floor lamp
    metal = b.mat("lamp_metal", Material(
        (rgb255(40, 40, 40), rgb255(90, 90, 90)), scale=0.2, octaves=3, seed=35))
    shade = b.mat("lamp_shade", Material(
        (rgb255(210, 190, 150), rgb255(245, 235, 210)), scale=0.1, octaves=4,
        stripes=((0.0, 0.0, 1.0), 0.04, 0.2, rgb255(180, 150, 110)), seed=36))
    lx, ly = X - 0.4, -Y + 0.4
    b.add("lamp_base", cylinder((lx, ly, 0), (lx, ly, 0.03), 0.15, 20), metal)
    b.add("lamp_pole", cylinder((lx, ly, 0.03), (lx, ly, 1.5), 0.012, 10), metal)
    b.add("lamp_shade", cylinder((lx, ly, 1.45), (lx, ly, 1.75), 0.22, 24, radius1=0.14), shade)


def _chair(b: _Builder, x: float, y: float, yaw: float, mat: str) -> None:
    R = rot_z(yaw)
    c = np.array([x, y, 0.0])
    b.add("chair_seat", box((0.44, 0.44, 0.04), c + [0, 0, 0.45], R), mat)
    b.add("chair_back", box((0.04, 0.44, 0.45), c + R @ [-0.2, 0, 0.7], R), mat)
    for dx in (-0.19, 0.19):
        for dy in (-0.19, 0.19):
            p = c + R @ np.array([dx, dy, 0.0])
            b.add("chair_leg", box((0.035, 0.035, 0.43), p + [0, 0, 0.215], R), mat)


def _plant(b: _Builder, seed: int, base: np.ndarray) -> None:
    """A potted plant (~0.35 m) whose pot stands on ``base`` (the table-top point)."""
    rng = _rng(seed, "plant")
    pot = b.mat("terracotta", Material(
        (rgb255(140, 62, 36), rgb255(210, 120, 80)), scale=0.05, octaves=5, contrast=1.8,
        spot_color=rgb255(225, 215, 195), spot_frac=0.12, spot_scale=0.03, grain=0.1,
        stripes=((0.0, 0.0, 1.0), 0.04, 0.12, rgb255(110, 50, 30)), seed=60))
    soil = b.mat("soil", Material(
        (rgb255(40, 26, 16), rgb255(100, 72, 48)), scale=0.02, octaves=4, contrast=1.6,
        grain=0.3, seed=61))
    leaf = b.mat("leaf", Material(
        (rgb255(30, 80, 24), rgb255(120, 180, 60)), scale=0.04, octaves=5, contrast=1.7,
        spot_color=rgb255(200, 210, 90), spot_frac=0.15, spot_scale=0.02, seed=62))
    stem = b.mat("stem", Material(
        (rgb255(60, 90, 30), rgb255(110, 140, 60)), scale=0.03, octaves=3, seed=63))
    prof = [(0.058, 0.0), (0.066, 0.04), (0.074, 0.085), (0.082, 0.115), (0.092, 0.118),
            (0.092, 0.135)]
    b.add("pot", transform(lathe(prof, 40), None, base), pot, ooi=True)
    b.add("soil", cylinder(base + [0, 0, 0.13], base + [0, 0, 0.138], 0.085, 40), soil, ooi=True)
    n_leaves = 22
    for k in range(n_leaves):
        az = 2.39996 * k + rng.uniform(-0.3, 0.3)  # golden-angle phyllotaxis
        el = rng.uniform(0.55, 1.35)
        length = rng.uniform(0.05, 0.16)
        start = base + np.array([0.02 * np.cos(az), 0.02 * np.sin(az), 0.135])
        direc = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        tip = start + direc * length
        b.add("stem", cylinder(start, tip, 0.004, 8), stem, ooi=True)
        # leaf: a flattened ellipsoid hanging from the stem tip, tilted downwards a little
        ll = rng.uniform(0.08, 0.13)
        lw = ll * rng.uniform(0.35, 0.5)
        v, f = sphere((0, 0, 0), 1.0, 20, scale=(ll / 2, lw / 2, 0.003))
        droop = rng.uniform(-0.5, 0.1)
        R = rot_z(az) @ rot_y(-droop) @ np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1]])
        centre = tip + R @ np.array([ll / 2 * 0.9, 0, 0])
        b.add("leaf", transform((v, f), R, centre), leaf, ooi=True)


def make_tabletop(seed: int) -> SimScene:
    b = _Builder()
    rng = _rng(seed, "room")
    X, Y, Z = 2.5, 2.0, 2.6
    _room(b, rng, X, Y, Z, rgb255(200, 196, 178))
    table = b.mat("table_wood", Material(
        (rgb255(96, 56, 28), rgb255(190, 128, 74)), scale=0.2, octaves=6, contrast=2.0,
        grain=0.28, spot_color=rgb255(70, 40, 20), spot_frac=0.05, spot_scale=0.03,
        stripes=((1.0, 0.0, 0.0), 0.12, 0.04, rgb255(70, 40, 20)), seed=70))
    rug = b.mat("rug", Material(
        (rgb255(120, 30, 40), rgb255(200, 120, 80)), scale=0.3, octaves=5, contrast=1.8,
        grid=(0.25, 0.03, 0.6), spot_color=rgb255(30, 40, 90), spot_frac=0.2, spot_scale=0.15,
        decals=(Decal((-1.2, -0.85, -0.1), (1.2, -0.75, 0.1), rgb255(230, 210, 160)),
                Decal((-1.2, 0.75, -0.1), (1.2, 0.85, 0.1), rgb255(230, 210, 160))), seed=71))
    chair = b.mat("chair_wood", Material(
        (rgb255(60, 40, 25), rgb255(130, 90, 55)), scale=0.2, octaves=5, contrast=1.5,
        stripes=((0.0, 0.0, 1.0), 0.03, 0.3, rgb255(50, 30, 20)), seed=72))
    b.add("rug", box((2.4, 1.8, 0.01), (0.0, 0.0, 0.005)), rug, casts_shadow=False)
    top_z = 0.76
    tc = np.array([0.1, 0.05])
    b.add("table_top", box((1.4, 0.9, 0.04), (tc[0], tc[1], top_z - 0.02)), table)
    for dx in (-0.64, 0.64):
        for dy in (-0.39, 0.39):
            leg_h = top_z - 0.04
            b.add("table_leg", box((0.05, 0.05, leg_h), (tc[0] + dx, tc[1] + dy, leg_h / 2)),
                  table)
    _chair(b, tc[0] - 0.95, tc[1] + 0.1, 0.0, chair)
    _chair(b, tc[0] + 0.95, tc[1] - 0.15, np.pi, chair)
    _chair(b, tc[0] + 0.2, tc[1] + 0.8, -np.pi / 2 + 0.3, chair)
    # things on the table, away from the plant
    mug = b.mat("mug", Material(
        (rgb255(30, 90, 160), rgb255(90, 160, 220)), scale=0.03, octaves=4, contrast=1.5,
        stripes=((0.0, 0.0, 1.0), 0.025, 0.3, rgb255(240, 240, 240)), seed=73))
    book = b.mat("table_book", Material(
        (rgb255(150, 30, 30), rgb255(220, 160, 120)), scale=0.05, octaves=5, contrast=2.0,
        spot_color=rgb255(20, 20, 20), spot_frac=0.25, spot_scale=0.03, seed=74))
    fruit = b.mat("fruit", Material(
        (rgb255(200, 120, 20), rgb255(250, 190, 60)), scale=0.03, octaves=4, contrast=1.4,
        spot_color=rgb255(90, 140, 40), spot_frac=0.2, seed=75))
    b.add("mug", cylinder((0.5, -0.22, top_z), (0.5, -0.22, top_z + 0.095), 0.04, 24), mug)
    b.add("book", box((0.22, 0.16, 0.035), (-0.38, 0.25, top_z + 0.0175), rot_z(0.3)), book)
    b.add("book", box((0.2, 0.14, 0.03), (-0.37, 0.24, top_z + 0.05), rot_z(0.1)), mug)
    for k in range(4):
        a = k * 1.7
        b.add("fruit", sphere((0.55 + 0.05 * np.cos(a), 0.3 + 0.05 * np.sin(a),
                               top_z + 0.035), 0.036, 16), fruit)
    base = np.array([0.0, 0.0, top_z])
    _plant(b, seed, base)
    return SimScene(
        "tabletop", seed, b.parts, b.materials,
        Lighting(direction=(0.45, 0.2, 1.0), ambient=0.5, diffuse=0.52, shadow=0.5),
        support_z=top_z,
        camera_bounds=(np.array([-X + 0.2, -Y + 0.2, 0.3]), np.array([X - 0.2, Y - 0.2,
                                                                      Z - 0.2])),
        rings=(Ring(15.0, 2.7), Ring(35.0, 2.5), Ring(55.0, 2.35)), indoor=True,
        description="potted plant on a wooden table in a furnished room (rug, chairs, "
                    "bookshelf, pictures, lamp)")


def make_stool(seed: int) -> SimScene:
    """The potted plant on a round stool under a knitted cloth that hangs to the floor (the
    set-up of the Mip-NeRF 360 bonsai): below the support surface lie the cloth's sides, not
    only the floor's skin of SfM points."""
    b = _Builder()
    rng = _rng(seed, "stoolroom")
    X, Y, Z = 2.5, 2.0, 2.6
    _room(b, rng, X, Y, Z, rgb255(205, 200, 190))
    cloth = b.mat("knit_cloth", Material(
        (rgb255(50, 30, 60), rgb255(120, 80, 130)), scale=0.08, octaves=5, contrast=1.6,
        grid=(0.012, 0.004, 0.45), grain=0.2, spot_color=rgb255(40, 25, 45), spot_frac=0.1,
        spot_scale=0.02, seed=80))
    rug = b.mat("rug", Material(
        (rgb255(40, 60, 70), rgb255(170, 180, 170)), scale=0.25, octaves=5, contrast=1.8,
        grid=(0.2, 0.03, 0.6), spot_color=rgb255(30, 40, 50), spot_frac=0.2, spot_scale=0.1,
        seed=81))
    b.add("rug", box((2.2, 1.6, 0.01), (0.0, 0.0, 0.005)), rug, casts_shadow=False)
    top_z = 0.55
    radius = 0.32
    # the cloth: a closed drum from just above the floor to the stool's top, its rim a touch
    # wider at the bottom where it hangs loose
    b.add("stool_cloth", cylinder((0.0, 0.0, 0.02), (0.0, 0.0, top_z), radius + 0.03, 48,
                                  radius1=radius), cloth)
    chair = b.mat("chair_wood", Material(
        (rgb255(60, 40, 25), rgb255(130, 90, 55)), scale=0.2, octaves=5, contrast=1.5,
        stripes=((0.0, 0.0, 1.0), 0.03, 0.3, rgb255(50, 30, 20)), seed=72))
    _chair(b, -1.1, 0.3, 0.2, chair)
    _chair(b, 1.0, -0.6, np.pi - 0.3, chair)
    base = np.array([0.0, 0.0, top_z])
    _plant(b, seed, base)
    return SimScene(
        "stool", seed, b.parts, b.materials,
        Lighting(direction=(0.4, 0.25, 1.0), ambient=0.5, diffuse=0.52, shadow=0.5),
        support_z=top_z,
        camera_bounds=(np.array([-X + 0.2, -Y + 0.2, 0.3]), np.array([X - 0.2, Y - 0.2,
                                                                      Z - 0.2])),
        rings=(Ring(10.0, 4.5), Ring(25.0, 4.2), Ring(40.0, 4.0)), indoor=True,
        description="potted plant on a stool under a knitted cloth that hangs to the floor, "
                    "in a furnished room")


# ------------------------------------------------------------------------------------------
# bicycle on a lawn
# ------------------------------------------------------------------------------------------
def _bicycle(b: _Builder) -> None:
    """A bicycle (~1.75 m) standing on both wheels at z = 0, along x."""
    frame = b.mat("bike_frame", Material(
        (rgb255(150, 20, 30), rgb255(230, 60, 60)), scale=0.15, octaves=4, contrast=1.6,
        stripes=((1.0, 0.0, 0.3), 0.12, 0.25, rgb255(240, 240, 240)), seed=80))
    tyre = b.mat("bike_tyre", Material(
        (rgb255(18, 18, 18), rgb255(70, 66, 60)), scale=0.05, octaves=3, contrast=1.5, seed=81))
    chrome = b.mat("chrome", Material(
        (rgb255(120, 124, 130), rgb255(225, 228, 232)), scale=0.04, octaves=3, contrast=1.5,
        seed=82))
    black = b.mat("bike_black", Material(
        (rgb255(20, 20, 22), rgb255(80, 76, 70)), scale=0.05, octaves=4, contrast=1.4,
        seed=83))
    r_wheel = 0.342
    axles = {"rear": np.array([-0.52, 0.0, r_wheel]), "front": np.array([0.52, 0.0, r_wheel])}
    for name, c in axles.items():
        b.add(f"{name}_tyre", torus(c, (0, 1, 0), r_wheel - 0.022, 0.022, 64, 10), tyre,
              ooi=True)
        b.add(f"{name}_rim", torus(c, (0, 1, 0), 0.3, 0.011, 64, 8), chrome, ooi=True)
        b.add(f"{name}_hub", cylinder(c - [0, 0.05, 0], c + [0, 0.05, 0], 0.022, 12), chrome,
              ooi=True)
        n_spokes = 18
        for k in range(n_spokes):
            a = 2 * np.pi * (k + 0.5 * (name == "front")) / n_spokes
            side = 0.035 if k % 2 else -0.035
            h = c + [0, side, 0]
            r = c + np.array([0.295 * np.cos(a), 0.0, 0.295 * np.sin(a)])
            b.add(f"{name}_spoke", cylinder(h, r, 0.0022, 6), chrome, ooi=True)
    B = np.array([-0.04, 0.0, 0.30])   # bottom bracket
    S = np.array([-0.17, 0.0, 0.82])   # seat cluster
    H1 = np.array([0.40, 0.0, 0.80])   # head tube top
    H2 = np.array([0.45, 0.0, 0.64])   # head tube bottom
    R, F = axles["rear"], axles["front"]
    b.add("seat_tube", cylinder(B, S + [-0.01, 0, 0.02], 0.017, 14), frame, ooi=True)
    b.add("top_tube", cylinder(S, H1, 0.015, 14), frame, ooi=True)
    b.add("down_tube", cylinder(B, H2, 0.021, 14), frame, ooi=True)
    b.add("head_tube", cylinder(H2 - [0.015, 0, -0.04 * -1], H1 + [-0.005, 0, 0.04], 0.022,
                                14), frame, ooi=True)
    for s in (-1, 1):
        y = np.array([0, 0.045 * s, 0])
        b.add("chain_stay", cylinder(B + y * 0.5, R + y, 0.009, 10), frame, ooi=True)
        b.add("seat_stay", cylinder(S + y * 0.3, R + y, 0.008, 10), frame, ooi=True)
        b.add("fork", cylinder(H2 + y * 0.5, F + y, 0.012, 10), frame, ooi=True)
    post_top = S + [-0.05, 0, 0.14]
    b.add("seat_post", cylinder(S, post_top, 0.0135, 12), chrome, ooi=True)
    b.add("saddle", sphere(post_top + [-0.02, 0, 0.025], 1.0, 20, scale=(0.13, 0.075, 0.028)),
          black, ooi=True)
    stem_top = H1 + [0.02, 0, 0.12]
    b.add("stem", cylinder(H1, stem_top, 0.014, 12), chrome, ooi=True)
    b.add("handlebar", cylinder(stem_top + [0.05, -0.23, 0], stem_top + [0.05, 0.23, 0],
                                0.011, 12), chrome, ooi=True)
    b.add("handlebar_mount", cylinder(stem_top, stem_top + [0.05, 0, 0], 0.012, 10), chrome,
          ooi=True)
    for s in (-1, 1):
        g = stem_top + [0.05, 0.23 * s, 0]
        b.add("grip", cylinder(g, g + [0, 0.1 * s, 0], 0.017, 12), black, ooi=True)
    # drive train: chain ring, cranks, pedals
    b.add("chainring", torus(B + [0, 0.06, 0], (0, 1, 0), 0.095, 0.006, 40, 6), chrome,
          ooi=True)
    for s, ang in ((1, 0.9), (-1, 0.9 + np.pi)):
        tip = B + np.array([0.17 * np.cos(ang), 0.075 * s, 0.17 * np.sin(ang)])
        b.add("crank", cylinder(B + [0, 0.07 * s, 0], tip, 0.011, 10), chrome, ooi=True)
        b.add("pedal", box((0.09, 0.1, 0.022), tip + [0, 0.06 * s, 0]), black, ooi=True)


def _garden(b: _Builder, seed: int) -> None:
    """A lawn with a gravel path, bushes, trees, a bench, a fence and some rocks."""
    rng = _rng(seed, "garden")
    G = 40.0
    grass = b.mat("grass", Material(
        (rgb255(40, 80, 22), rgb255(130, 170, 60)), scale=0.8, octaves=7, contrast=1.6,
        spot_color=rgb255(120, 100, 50), spot_frac=0.05, spot_scale=1.0, grain=0.45, seed=90,
        decals=(Decal((-G, 1.6, -1), (G, 2.8, 0.01), rgb255(170, 150, 120), 0.5),)))
    bush = b.mat("bush", Material(
        (rgb255(20, 60, 18), rgb255(90, 150, 50)), scale=0.4, octaves=6, contrast=1.9,
        grain=0.4, spot_color=rgb255(170, 180, 60), spot_frac=0.08, seed=91))
    bark = b.mat("bark", Material(
        (rgb255(50, 36, 24), rgb255(120, 96, 70)), scale=0.3, octaves=5, contrast=1.6,
        stripes=((0.0, 0.0, 1.0), 0.07, 0.3, rgb255(30, 22, 16)), grain=0.2, seed=92))
    canopy = b.mat("canopy", Material(
        (rgb255(24, 70, 24), rgb255(110, 160, 70)), scale=0.7, octaves=6, contrast=1.9,
        grain=0.45, spot_color=rgb255(40, 40, 20), spot_frac=0.1, seed=93))
    wood = b.mat("bench_wood", Material(
        (rgb255(110, 76, 44), rgb255(180, 140, 90)), scale=0.3, octaves=5, contrast=1.5,
        stripes=((1.0, 1.0, 0.0), 0.12, 0.15, rgb255(70, 46, 28)), seed=94))
    stone = b.mat("stone", Material(
        (rgb255(90, 88, 84), rgb255(180, 176, 168)), scale=0.2, octaves=5, contrast=1.8,
        spot_color=rgb255(110, 130, 60), spot_frac=0.15, seed=95))
    b.add("lawn", box((2 * G, 2 * G, 0.2), (0, 0, -0.1)), grass, casts_shadow=False)
    spots = _scatter(rng, 16, 4.8, 10.0, lambda x, y: 1.2 < y < 3.2, 1.6)
    for x, y, yaw in spots:
        r = rng.uniform(0.5, 1.0)
        scale = (1.0, rng.uniform(0.7, 1.2), rng.uniform(0.7, 1.0))
        b.add("bush", blob((x, y, 0.25 * r), r, rng, 0.3, scale=scale, segments=24), bush)
    trees = _scatter(rng, 14, 11.0, 28.0, lambda x, y: 1.0 < y < 3.4, 4.0)
    for x, y, yaw in trees:
        h = rng.uniform(3.0, 5.5)
        r = rng.uniform(0.12, 0.25)
        b.add("trunk", cylinder((x, y, -0.1), (x, y, h), r, 14, radius1=r * 0.6), bark)
        cr = rng.uniform(1.5, 2.6)
        b.add("canopy", blob((x, y, h + cr * 0.6), cr, rng, 0.3, scale=(1, 1, 0.9), segments=28),
              canopy)
    for x, y, yaw in _scatter(rng, 12, 3.5, 14.0, lambda x, y: 1.2 < y < 3.2, 1.0):
        r = rng.uniform(0.1, 0.3)
        b.add("rock", blob((x, y, 0.2 * r), r, rng, 0.35, scale=(1.3, 1.0, 0.7), segments=14),
              stone)
    # bench beside the path and a fence behind the lawn
    bx, by = 1.5, 3.6
    for k in range(4):
        b.add("bench_slat", box((1.6, 0.09, 0.04), (bx, by + 0.11 * k - 0.16, 0.45)), wood)
    b.add("bench_back", box((1.6, 0.04, 0.35), (bx, by + 0.26, 0.75)), wood)
    for dx in (-0.7, 0.7):
        b.add("bench_leg", box((0.06, 0.45, 0.43), (bx + dx, by, 0.215)), wood)
    fy = -9.0
    for x in np.arange(-12.0, 12.5, 2.0):
        b.add("fence_post", box((0.1, 0.1, 1.2), (x, fy, 0.6)), wood)
    for z in (0.4, 0.9):
        b.add("fence_rail", box((24.2, 0.05, 0.12), (0.0, fy + 0.07, z)), wood)


def make_bicycle(seed: int) -> SimScene:
    b = _Builder()
    _bicycle(b)
    _garden(b, seed)
    return SimScene(
        "bicycle", seed, b.parts, b.materials,
        Lighting(direction=(0.5, -0.35, 0.8), ambient=0.5, diffuse=0.6, shadow=0.55,
                 clouds=0.5),
        support_z=0.0,
        camera_bounds=(np.array([-30.0, -30.0, 0.3]), np.array([30.0, 30.0, 30.0])),
        rings=(Ring(15.0, 2.5), Ring(32.0, 2.35), Ring(50.0, 2.2)), indoor=False,
        description="bicycle with spoked wheels on a lawn with a path, bushes, trees, rocks, "
                    "a bench and a fence")


# ------------------------------------------------------------------------------------------
# toy car among clutter on a workbench
# ------------------------------------------------------------------------------------------
def _toycar(b: _Builder, base: np.ndarray) -> None:
    """A toy car (~0.24 m long) standing on its four wheels at ``base``."""
    body = b.mat("toy_body", Material(
        (rgb255(200, 140, 0), rgb255(255, 210, 40)), scale=0.03, octaves=5, contrast=1.6,
        spot_color=rgb255(60, 40, 20), spot_frac=0.05, spot_scale=0.015,
        stripes=((1.0, 0.0, 0.0), 0.05, 0.15, rgb255(30, 30, 140)), seed=100))
    glass = b.mat("toy_glass", Material(
        (rgb255(30, 40, 60), rgb255(110, 140, 170)), scale=0.02, octaves=4, contrast=1.5,
        seed=101))
    tyre = b.mat("toy_tyre", Material(
        (rgb255(15, 15, 15), rgb255(70, 70, 70)), scale=0.01, octaves=3, contrast=1.4,
        seed=102))
    rw = 0.028
    b.add("car_body", box((0.24, 0.11, 0.05), base + [0, 0, rw + 0.03]), body, ooi=True)
    cab = np.array([[-0.07, -0.05, 0.0], [0.05, -0.05, 0.0], [0.05, 0.05, 0.0],
                    [-0.07, 0.05, 0.0], [-0.06, -0.045, 0.045], [0.02, -0.045, 0.045],
                    [0.02, 0.045, 0.045], [-0.06, 0.045, 0.045]])
    b.add("car_cabin", hexahedron(cab + base + [0, 0, rw + 0.055]), glass, ooi=True)
    b.add("car_roof", box((0.075, 0.088, 0.006), base + [-0.02, 0, rw + 0.103]), body, ooi=True)
    for dx in (-0.075, 0.075):
        for dy in (-0.058, 0.058):
            b.add("car_wheel", _wheel(base + np.array([dx, dy, rw]), rw, 0.02,
                                      np.array([0, 1.0, 0]), 20), tyre, ooi=True)
    b.add("car_antenna", cylinder(base + [-0.1, 0.04, rw + 0.055], base + [-0.11, 0.04, 0.18],
                                  0.0015, 6), tyre, ooi=True)


def make_toycar(seed: int) -> SimScene:
    b = _Builder()
    rng = _rng(seed, "workshop")
    X, Y, Z = 2.0, 1.8, 2.4
    _room(b, rng, X, Y, Z, rgb255(170, 180, 160))
    top_z = 0.9
    bench = b.mat("bench_top", Material(
        (rgb255(120, 90, 60), rgb255(200, 170, 130)), scale=0.2, octaves=6, contrast=1.6,
        spot_color=rgb255(80, 66, 50), spot_frac=0.04, spot_scale=0.06, grain=0.12, seed=110))
    pegboard = b.mat("pegboard", Material(
        (rgb255(150, 120, 80), rgb255(200, 170, 120)), scale=0.3, octaves=4,
        grid=(0.05, 0.008, 0.8), seed=111))
    b.add("bench_top", box((1.6, 0.8, 0.05), (0.1, 0.2, top_z - 0.025)), bench)
    for dx in (-0.72, 0.72):
        for dy in (-0.33, 0.33):
            leg_h = top_z - 0.05
            b.add("bench_leg", box((0.06, 0.06, leg_h), (0.1 + dx, 0.2 + dy, leg_h / 2)), bench)
    b.add("pegboard", box((1.6, 0.02, 0.9), (0.1, Y - 0.02, top_z + 0.6)), pegboard,
          casts_shadow=False)
    base = np.array([0.0, 0.0, top_z])
    _toycar(b, base)
    # clutter close around the car: tools, cans, boxes, a tape roll, screws
    colours = [rgb255(200, 40, 40), rgb255(40, 120, 200), rgb255(60, 160, 70),
               rgb255(230, 200, 60), rgb255(150, 80, 180), rgb255(230, 120, 40)]
    mats = []
    for k, col in enumerate(colours):
        mats.append(b.mat(f"clutter{k}", Material(
            (tuple(c * 0.45 for c in col), col), scale=0.03, octaves=4, contrast=1.7,
            spot_color=rgb255(240, 240, 230), spot_frac=0.05, spot_scale=0.01,
            seed=120 + k)))
    b.mat("chrome_tool", Material(
        (rgb255(120, 124, 130), rgb255(220, 222, 226)), scale=0.02, octaves=3, seed=130))
    spots = _scatter(rng, 12, 0.17, 0.6, lambda x, y: False, 0.11,
                     bounds=(-0.62, 0.82, -0.14, 0.52))
    for k, (x, y, yaw) in enumerate(spots):
        m = mats[k % len(mats)]
        kind = k % 5
        c = np.array([x, y, top_z])
        if kind == 0:
            b.add("can", cylinder(c, c + [0, 0, 0.12], 0.033, 20), m)
        elif kind == 1:
            s = rng.uniform(0.05, 0.1)
            b.add("box", box((s, s * 1.4, s * 0.8), c + [0, 0, s * 0.4], rot_z(yaw)), m)
        elif kind == 2:
            b.add("tape", torus(c + [0, 0, 0.018], (0, 0, 1), 0.04, 0.018, 32, 10), m)
        elif kind == 3:
            R = rot_z(yaw)
            b.add("screwdriver_handle", cylinder(c + [0, 0, 0.012], c + [0, 0, 0.012] +
                                                 R @ [0.09, 0, 0], 0.012, 12), m)
            b.add("screwdriver_shaft", cylinder(c + [0, 0, 0.012] + R @ [0.09, 0, 0],
                                                c + [0, 0, 0.012] + R @ [0.19, 0, 0], 0.003,
                                                8), "chrome_tool")
        else:
            b.add("mug", cylinder(c, c + [0, 0, 0.09], 0.036, 20), m)
    return SimScene(
        "toycar", seed, b.parts, b.materials,
        Lighting(direction=(-0.3, -0.4, 1.0), ambient=0.5, diffuse=0.52, shadow=0.5),
        support_z=top_z,
        camera_bounds=(np.array([-X + 0.2, -Y + 0.2, 0.3]), np.array([X - 0.2, Y - 0.2,
                                                                      Z - 0.2])),
        rings=(Ring(20.0, 4.0), Ring(40.0, 3.6), Ring(60.0, 3.3)), indoor=True,
        description="toy car on a workbench surrounded by tools, cans, boxes and a tape roll")


SCENE_BUILDERS: dict[str, Callable[[int], SimScene]] = {
    "aircraft": make_aircraft,
    "tabletop": make_tabletop,
    "bicycle": make_bicycle,
    "toycar": make_toycar,
    "stool": make_stool,
}
