"""Simulated drone captures: orbit rings around the OOI, rendered views with ground truth.

``simulate_capture`` gives a ``core.types.Capture`` like a real inspection flight (views in
capture order, one per second, camera intrinsics and poses, images, exact OOI masks, points on
the OOI surface); ``simulate_stream`` renders a continuous orbit frame by frame for the
streaming path (a drone flying at constant speed, camera at ``fps``).
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass, field
from typing import Iterator, Optional, Sequence, Union

import numpy as np

from ..core.geometry import look_at
from ..core.types import Capture, CameraIntrinsics, InputError, Pose, View
from .render import Renderer, intrinsics_from_fov
from .scene import Ring, SimScene
from .scenes import SCENE_BUILDERS

SCENES: tuple[str, ...] = tuple(SCENE_BUILDERS)
STAMP_BASE_NS = 1_700_000_000 * 10 ** 9  # first frame's stamp (2023-11-14T22:13:20Z)


@dataclass
class SimConfig:
    """Options of a simulated capture (written next to outputs as the resolved config)."""

    scene: str = "aircraft"  # one of SCENES
    n_views: int = 60  # number of images in the capture
    width: int = 320  # image width in pixels
    height: int = 240  # image height in pixels
    hfov_deg: float = 60.0  # horizontal field of view of the pinhole camera
    seed: int = 0  # scene layout, textures, camera jitter and sensor noise
    rings: Optional[list[list[float]]] = None  # [[elevation_deg, distance/OOI radius], ...]
    supersample: int = 2  # sub-samples per pixel side (2 = 2x2 anti-aliasing, mask majority)
    shade_subsamples: bool = False  # shade every sub-sample (texture integrated over the pixel,
    # ~4x the texturing cost) rather than once per pixel inside a part (point-sampled texture)
    aim_jitter: float = 0.05  # std of the aim point offset, in OOI radii
    roll_jitter_deg: float = 1.5  # std of camera roll about the optical axis
    frame_interval_s: float = 1.0  # time between images (stamps)
    sensor_noise: float = 1.5  # std of Gaussian pixel noise, 0-255 units
    exposure_jitter: float = 0.03  # std of the per-frame exposure gain (auto exposure)
    gt_points: int = 20000  # points sampled on the OOI surface for evaluation
    distortion: Optional[list[float]] = None  # plumb_bob [k1, k2, p1, p2, k3]; None = pinhole
    vignetting: float = 0.0  # the lens's light falloff toward the corners (gain 1 - v r^2, r
    # = distance from the principal point over the half diagonal; 0 = none, 0.4 = corners at 60%)
    demosaic: bool = False  # a camera's optics and Bayer sensor: the lens's low-pass, one
    # colour per pixel (RGGB), the noise drawn on that mosaic, the image demosaiced (OpenCV
    # edge-aware) -- a real camera's softer image and correlated noise
    arc_deg: float = 360.0  # azimuth span each ring flies: 360 = full orbits; less = a partial
    # orbit (an object beside a wall or a no-fly zone), views spread evenly over the arc


@dataclass
class SimCapture:
    """A simulated capture with its scene (ground-truth geometry and distance helpers)."""

    capture: Capture
    scene: SimScene
    config: SimConfig
    depths: list[np.ndarray] = field(default_factory=list)  # [H, W] float32 per view, inf=sky

    def object_truth(self, index: int) -> np.ndarray:
        """View ``index`` as an exact object-only model would render it over black: float32
        [H, W, 3] in 0..1, the view's own exposure, no sensor noise, outline pixels scaled by
        the object's sub-sample coverage.

        The captured image's outline pixels mix the object with whatever lies behind it, which
        no object-only model can reproduce; scoring held-out renders against this image inside
        the mask measures the object alone (see benchmarks/bench_train.py).
        """
        cfg = self.config
        view = self.capture.views[index]
        rng = _view_rng(cfg.seed, index)
        exposure = float(np.clip(1.0 + rng.normal(0, cfg.exposure_jitter), 0.8, 1.2))
        res = Renderer(self.scene).render(view.camera, view.pose, cfg.supersample, None, 0.0,
                                          exposure, object_only=True,
                                          shade_subsamples=cfg.shade_subsamples,
                                          vignetting=cfg.vignetting, demosaic=cfg.demosaic)
        img = res.rgb.astype(np.float32) / 255.0
        return img


def _view_rng(seed: int, index: int) -> np.random.Generator:
    """The random stream of view ``index`` (its exposure draw first, then sensor noise)."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), 0xF4A3, int(index)]))


def _check_scene(name: str) -> None:
    if name not in SCENE_BUILDERS:
        raise InputError(f"unknown scene {name!r}; choose one of {', '.join(SCENES)} "
                         "(ooi-seg simulate --list)")


@functools.lru_cache(maxsize=8)
def _cached_scene(name: str, seed: int) -> SimScene:
    return SCENE_BUILDERS[name](seed)


def make_scene(name: str, seed: int = 0) -> SimScene:
    """The scene ``name`` (see ``SCENES``) built with ``seed`` (cached; treat as read-only)."""
    _check_scene(name)
    return _cached_scene(name, int(seed))


def _rings(scene: Optional[SimScene], rings: Optional[Sequence]) -> list[Ring]:
    """Validated rings: ``rings`` as given, or the scene's defaults when None."""
    if rings is None:
        return list(scene.rings) if scene is not None else []
    out = []
    for r in rings:
        if isinstance(r, Ring):
            out.append(r)
            continue
        try:
            e, d = (float(x) for x in r)
            if not (np.isfinite(e) and np.isfinite(d)):
                raise ValueError
        except (TypeError, ValueError):
            raise InputError(f"ring {r!r} is not (elevation_deg, distance_factor)") from None
        if not (-10.0 < e < 90.0) or d <= 0:
            raise InputError(f"ring {r!r}: elevation must be in (-10, 90) degrees and the "
                             "distance factor positive")
        out.append(Ring(e, d))
    if not out:
        raise InputError("rings is empty; give at least one (elevation_deg, distance_factor)")
    return out


def _place(scene: SimScene, center: np.ndarray, direction: np.ndarray, dist: float) -> np.ndarray:
    """Camera centre along ``direction`` from ``center``, pulled in to stay in the flight box
    and clear of surfaces (a drone cannot fly through walls or bushes)."""
    lo, hi = scene.camera_bounds
    clear = 0.05 * scene.ooi_radius
    s = 1.0
    for _ in range(60):
        eye = center + direction * dist * s
        if np.all(eye >= lo) and np.all(eye <= hi) and \
                scene.distance_to_surface(eye[None])[0] > clear:
            return eye
        s *= 0.96
    return center + direction * dist * s


def _roll(pose: Pose, angle: float) -> Pose:
    """Rotate the camera about its optical axis by ``angle`` (radians)."""
    c, s = np.cos(angle), np.sin(angle)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return Pose(pose.R @ Rz, pose.t.copy())


def orbit_poses(scene: SimScene, n_views: int, rings: Optional[Sequence] = None,
                seed: int = 0, aim_jitter: float = 0.05,
                roll_jitter_deg: float = 1.5, arc_deg: float = 360.0) -> list[Pose]:
    """Camera-to-world poses of a drone inspection orbit, in flight order.

    Views are shared between rings in proportion to each ring's circumference (at least 3 per
    ring); each ring is flown in the same direction, starting at a ring-dependent azimuth. The
    camera looks at the OOI centre with a small random aim offset and roll. ``arc_deg`` < 360
    flies each ring over that azimuth span only (first and last view at its ends), all rings
    over the same side of the object.
    """
    if n_views < 1:
        raise InputError(f"n_views={n_views}: need at least one view")
    if not (0.0 < arc_deg <= 360.0):
        raise InputError(f"arc_deg={arc_deg} must be within (0, 360] degrees")
    rs = _rings(scene, rings)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x0CA3]))
    center = scene.ooi_center
    radius = scene.ooi_radius
    circ = np.array([np.cos(np.radians(r.elevation_deg)) * r.distance for r in rs])
    share = circ / circ.sum() * n_views
    counts = np.floor(share).astype(int)
    for k in np.argsort(-(share - counts))[: n_views - counts.sum()]:
        counts[k] += 1
    if n_views >= 3 * len(rs):
        while counts.min() < 3:
            counts[np.argmin(counts)] += 1
            counts[np.argmax(counts)] -= 1
    poses = []
    for i, (ring, m) in enumerate(zip(rs, counts)):
        e = np.radians(ring.elevation_deg)
        # a partial orbit flies every ring over the same side
        a0 = rng.uniform(0, 0.2) + (0.6 * i if arc_deg == 360.0 else 0.0)
        for j in range(m):
            if arc_deg < 360.0:
                a = a0 + np.radians(arc_deg) * j / max(m - 1, 1)
            else:
                a = a0 + 2 * np.pi * j / max(m, 1)
            direction = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
            eye = _place(scene, center, direction, ring.distance * radius)
            aim = center + rng.normal(0, aim_jitter * radius, 3)
            pose = look_at(eye, aim)
            poses.append(_roll(pose, np.radians(rng.normal(0, roll_jitter_deg))))
    return poses


def simulate_capture(scene_name: str, n_views: int = 60, width: int = 320, height: int = 240,
                     seed: int = 0, rings: Optional[Sequence] = None,
                     config: Optional[SimConfig] = None, **options) -> SimCapture:
    """Render a drone-orbit capture of scene ``scene_name`` with exact ground truth.

    ``options`` are further ``SimConfig`` fields (hfov_deg, supersample, sensor_noise, ...);
    a full ``config`` overrides all other arguments.
    """
    if config is None:
        try:
            ring_list = None if rings is None else [
                [float(r.elevation_deg), float(r.distance)] for r in _rings(None, rings)]
            config = SimConfig(scene=scene_name, n_views=n_views, width=width, height=height,
                               seed=seed, rings=ring_list, **options)
        except TypeError as exc:
            raise InputError(f"bad simulate option: {exc}") from None
    cfg = config
    _check_scene(cfg.scene)
    if cfg.width < 8 or cfg.height < 8:
        raise InputError(f"image size {cfg.width}x{cfg.height} is too small; use at least 8x8")
    if not (5.0 <= cfg.hfov_deg <= 150.0):
        raise InputError(f"hfov_deg={cfg.hfov_deg} must be within 5..150 degrees")
    scene = make_scene(cfg.scene, cfg.seed)
    try:
        cam = intrinsics_from_fov(cfg.width, cfg.height, cfg.hfov_deg, cfg.distortion)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    poses = orbit_poses(scene, cfg.n_views, cfg.rings, cfg.seed, cfg.aim_jitter,
                        cfg.roll_jitter_deg, cfg.arc_deg)
    renderer = Renderer(scene)
    views, depths = [], []
    for k, pose in enumerate(poses):
        rng = _view_rng(cfg.seed, k)
        exposure = float(np.clip(1.0 + rng.normal(0, cfg.exposure_jitter), 0.8, 1.2))
        res = renderer.render(cam, pose, cfg.supersample, rng, cfg.sensor_noise, exposure,
                              shade_subsamples=cfg.shade_subsamples, vignetting=cfg.vignetting,
                              demosaic=cfg.demosaic)
        stamp = STAMP_BASE_NS + int(round(k * cfg.frame_interval_s * 1e9))
        views.append(View(key=str(stamp), stamp_ns=stamp, camera=cam, pose=pose,
                          image=res.rgb, gt_mask=res.mask, source=f"sim:{cfg.scene}"))
        depths.append(res.depth)
    meta = scene.summary()
    meta["seed"] = int(cfg.seed)
    meta["config"] = asdict(cfg)
    if not cfg.shade_subsamples:  # recorded only when on: captures (and the demo bag)
        del meta["config"]["shade_subsamples"]  # simulated before the option keep their bytes
    if cfg.arc_deg == 360.0:  # likewise
        del meta["config"]["arc_deg"]
    if not cfg.vignetting:  # likewise
        del meta["config"]["vignetting"]
    if not cfg.demosaic:  # likewise
        del meta["config"]["demosaic"]
    capture = Capture(views=views, source=f"sim:{cfg.scene}:seed{cfg.seed}",
                      gt_ooi_points=scene.sample_ooi_points(cfg.gt_points, cfg.seed), meta=meta)
    return SimCapture(capture, scene, cfg, depths)


def stream_pose(scene: SimScene, t: float, speed: Optional[float] = None,
                rings: Optional[Sequence] = None, seed: int = 0,
                aim_jitter: float = 0.05) -> Pose:
    """Camera pose at time ``t`` (s) of a drone orbiting the OOI at ``speed`` m/s.

    The drone flies the mean ring radius and climbs/descends slowly between the lowest and the
    highest ring elevation (one cycle per two orbits); aim wobble and roll are smooth in time.
    Default speed: one orbit in 40 s.
    """
    rs = _rings(scene, rings)
    radius = scene.ooi_radius
    e_lo = min(r.elevation_deg for r in rs)
    e_hi = max(r.elevation_deg for r in rs)
    dist = float(np.mean([r.distance for r in rs])) * radius
    horiz = dist * np.cos(np.radians((e_lo + e_hi) / 2))
    if speed is None:
        speed = 2 * np.pi * horiz / 40.0
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x57EA]))
    ph = rng.uniform(0, 2 * np.pi, 8)
    omega = speed / max(horiz, 1e-9)
    a = ph[0] + omega * t
    e = np.radians(e_lo + (e_hi - e_lo) * 0.5 * (1 - np.cos(omega * t / 2)))
    direction = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    center = scene.ooi_center
    eye = _place(scene, center, direction, dist)
    wob = np.array([np.sin(0.7 * t + ph[1]) + 0.5 * np.sin(1.9 * t + ph[2]),
                    np.sin(0.5 * t + ph[3]) + 0.5 * np.sin(2.3 * t + ph[4]),
                    np.sin(0.6 * t + ph[5])]) * (aim_jitter * radius / 1.2)
    pose = look_at(eye, center + wob)
    return _roll(pose, np.radians(1.0) * np.sin(0.8 * t + ph[6]))


def simulate_stream(scene: Union[str, SimScene], fps: float = 30.0, duration_s: float = 10.0,
                    width: int = 320, height: int = 240, seed: int = 0,
                    speed: Optional[float] = None, hfov_deg: float = 60.0,
                    supersample: int = 1, sensor_noise: float = 1.5
                    ) -> Iterator[tuple[int, np.ndarray, Pose, np.ndarray]]:
    """Lazily render a continuous orbit: yields ``(stamp_ns, rgb, pose, mask)`` per frame.

    Frames are rendered only when asked for (the generator does no work ahead). The camera
    intrinsics are ``intrinsics_from_fov(width, height, hfov_deg)``.
    """
    if fps <= 0 or duration_s < 0:
        raise InputError(f"fps={fps} must be > 0 and duration_s={duration_s} >= 0")
    sc = make_scene(scene, seed) if isinstance(scene, str) else scene
    cam: CameraIntrinsics = intrinsics_from_fov(width, height, hfov_deg)
    renderer = Renderer(sc)
    n = int(np.floor(duration_s * fps + 1e-9))
    for k in range(n):
        t = k / fps
        pose = stream_pose(sc, t, speed, None, seed)
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x57EB, k]))
        res = renderer.render(cam, pose, supersample, rng, sensor_noise)
        stamp = STAMP_BASE_NS + int(round(t * 1e9))
        yield stamp, res.rgb, pose, res.mask
