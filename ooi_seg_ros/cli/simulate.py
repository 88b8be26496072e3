"""``ooi-seg simulate``: render a simulated drone capture to a bag (.mcap) or a folder."""

from __future__ import annotations

import argparse
import importlib
import time

from ..core.types import InputError


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "simulate", help="render a simulated drone orbit capture with ground truth",
        description="Render a drone-orbit capture of a procedural scene (images, intrinsics, "
                    "poses, exact OOI masks, OOI surface points). OUT ending in .mcap is "
                    "written as a ROS 2 bag, anything else as a folder.")
    p.add_argument("--scene", default="aircraft", help="scene name (see --list)")
    p.add_argument("--out", help="output bag (*.mcap) or folder")
    p.add_argument("--views", type=int, default=60, help="number of images (default 60)")
    p.add_argument("--size", default="320x240", help="image size WxH (default 320x240)")
    p.add_argument("--seed", type=int, default=0, help="scene/camera/noise seed (default 0)")
    p.add_argument("--fov", type=float, default=60.0,
                   help="horizontal field of view in degrees (default 60)")
    p.add_argument("--supersample", type=int, default=2,
                   help="anti-aliasing sub-samples per pixel side (default 2; 1 = off)")
    p.add_argument("--rings", default=None,
                   help="orbit rings as ELEV:DIST,... (elevation in degrees, distance in OOI "
                        "radii), e.g. 15:2.5,35:2.3; default: the scene's own rings")
    p.add_argument("--arc", type=float, default=360.0,
                   help="azimuth span of each ring in degrees (default 360, a full orbit; "
                        "e.g. 180 for an object beside a wall)")
    p.add_argument("--distortion", default=None,
                   help="plumb_bob lens distortion k1,k2[,p1,p2,k3] (default: ideal pinhole)")
    p.add_argument("--noise", type=float, default=1.5,
                   help="sensor noise std in 0-255 grey levels (default 1.5; a dim hangar ~6)")
    p.add_argument("--exposure-jitter", type=float, default=0.03,
                   help="std of the per-frame exposure gain, auto exposure (default 0.03)")
    p.add_argument("--vignetting", type=float, default=0.0,
                   help="lens light falloff: gain 1 - V r^2, r from the centre over the half "
                        "diagonal (default 0; 0.4 = corners at 60%%)")
    p.add_argument("--demosaic", action="store_true",
                   help="a Bayer sensor: one colour per pixel (RGGB), the noise on that mosaic, "
                        "the image demosaiced as a camera delivers it (default: every pixel "
                        "sees all three colours, independent noise)")
    p.add_argument("--jpeg", type=int, default=0, metavar="Q",
                   help="write the images as JPEG at quality Q (1-100): CompressedImage in a "
                        "bag, .jpg files in a folder, as most drone cameras deliver them "
                        "(default 0: lossless)")
    p.add_argument("--list", action="store_true", help="print the scene names and exit")
    p.set_defaults(func=run)


def parse_size(text: str) -> tuple[int, int]:
    """``"320x240"`` -> (320, 240); InputError with the expected form otherwise."""
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--size {text!r} is not WxH (e.g. --size 320x240)") from None
    if w < 8 or h < 8 or w > 8192 or h > 8192:
        raise InputError(f"--size {text!r}: width and height must be within 8..8192")
    return w, h


def parse_rings(text: str | None) -> list[list[float]] | None:
    """``"15:2.5,35:2.3"`` -> [[15.0, 2.5], [35.0, 2.3]]; None stays None."""
    if text is None:
        return None
    rings = []
    for item in text.split(","):
        try:
            e, d = (float(x) for x in item.split(":"))
        except ValueError:
            raise InputError(f"--rings item {item!r} is not ELEV:DIST (e.g. --rings "
                             "15:2.5,35:2.3)") from None
        rings.append([e, d])
    return rings


def parse_distortion(text: str | None) -> list[float] | None:
    """``"-0.1,0.02"`` -> [-0.1, 0.02] (plumb_bob k1, k2[, p1, p2, k3])."""
    if text is None:
        return None
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        raise InputError(f"--distortion {text!r} is not a comma-separated list of numbers "
                         "(e.g. --distortion -0.1,0.02)") from None
    if not 1 <= len(vals) <= 5:
        raise InputError(f"--distortion {text!r}: give 1 to 5 plumb_bob coefficients "
                         "k1,k2,p1,p2,k3")
    return vals


def run(args: argparse.Namespace) -> int:
    from ..sim import SCENES, make_scene, simulate_capture

    if args.list:
        for name in SCENES:
            print(f"{name:10s} {make_scene(name, 0).description}")
        return 0
    if args.scene not in SCENES:
        raise InputError(f"unknown scene {args.scene!r}; choose one of {', '.join(SCENES)}")
    if not args.out:
        raise InputError("no output given; pass --out OUT.mcap (a bag) or --out DIR (a folder)")
    if args.views < 1:
        raise InputError(f"--views {args.views}: need at least 1 view")
    if args.supersample < 1 or args.supersample > 4:
        raise InputError(f"--supersample {args.supersample}: use 1..4")
    if not 0 < args.arc <= 360:
        raise InputError(f"--arc {args.arc}: use a span within (0, 360] degrees")
    for flag, val, hi in (("--noise", args.noise, 64.0),
                          ("--exposure-jitter", args.exposure_jitter, 0.5),
                          ("--vignetting", args.vignetting, 0.95)):
        if not 0.0 <= val <= hi:
            raise InputError(f"{flag} {val}: use a value within [0, {hi}]")
    if not 0 <= args.jpeg <= 100:
        raise InputError(f"--jpeg {args.jpeg}: use a quality within 1..100 (0 = lossless)")
    w, h = parse_size(args.size)
    rings = parse_rings(args.rings)
    distortion = parse_distortion(args.distortion)
    try:
        capture_io = importlib.import_module("ooi_seg_ros.capture_io")
    except ModuleNotFoundError as exc:
        if exc.name != "ooi_seg_ros.capture_io":
            raise
        raise InputError("this installation has no capture writer (ooi_seg_ros.capture_io); "
                         "update the package") from None
    t0 = time.monotonic()
    sim = simulate_capture(args.scene, n_views=args.views, width=w, height=h, seed=args.seed,
                           rings=rings, hfov_deg=args.fov, supersample=args.supersample,
                           distortion=distortion, arc_deg=args.arc,
                           sensor_noise=args.noise, exposure_jitter=args.exposure_jitter,
                           vignetting=args.vignetting, demosaic=args.demosaic)
    t1 = time.monotonic()
    capture_io.write_capture(sim.capture, args.out, jpeg_quality=args.jpeg)
    cov = [float(v.gt_mask.mean()) for v in sim.capture.views]
    print(f"scene {args.scene} (seed {args.seed}): {len(sim.capture)} views {w}x{h}, "
          f"OOI diagonal {sim.scene.ooi_diagonal:.3g} m, OOI covers "
          f"{100 * min(cov):.1f}-{100 * max(cov):.1f}% of each image; rendered in "
          f"{t1 - t0:.1f} s")
    print(f"wrote {args.out}")
    return 0
