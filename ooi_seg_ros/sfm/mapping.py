"""SfM with unknown poses: pycolmap incremental mapping over an image folder.

Used when a capture comes without poses (a plain image folder, a hand-held photo set). Features
are SIFT (pycolmap), pairs are sequential (photos taken in order along a path) for large sets and
exhaustive for small ones, and the largest reconstructed model is returned as a ``Capture``
with the estimated camera-to-world poses plus its ``SfmCloud``.

Exhaustive matching can tie photos of different places together (similar views from opposite
sides of an object): on 58-59 of the real bonsai's photos every exhaustive run put a block of
cameras, or most of them, in the wrong place, with a good reprojection error. Such a model
shows as a jump in the camera path along the photos' name order (``path_jump``) and as cameras
whose image does not hold the point the others converge on (``looking_away``). When exhaustive
matching gives either, the same features are matched again sequentially (neighbours in name
order only) and the better model is kept: first the one whose path steps evenly, then the one
with more registered cameras that frame the convergence point (the exhaustive one on a tie).
On those photos the sequential model placed every camera within 1.1% of the orbit radius in
three runs of three; on 37 photos (10 deg apart) the exhaustive model, with 2 cameras looking
away, stays the better one.
"""

from __future__ import annotations

import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ..core.types import CameraIntrinsics, Capture, InputError, SfmCloud
from .colmap_io import load_colmap_model

LOG = logging.getLogger(__name__)


@dataclass
class MappingConfig:
    """Options of the unknown-pose mapping route."""

    max_image_size: int = 1600  # SIFT runs on images resized so the long side is at most this
    max_num_features: int = 8192  # SIFT features kept per image
    exhaustive_max_images: int = 60  # match every pair up to this many images, else sequential
    sequential_overlap: int = 12  # sequential matching: neighbours matched on each side
    quadratic_overlap: bool = True  # sequential matching: also match at 2^k offsets
    sequential_rematch: bool = True  # exhaustive matching gave a camera path jump or cameras
    # looking away: match the same features sequentially too and keep the better model
    num_threads: int = -1  # pycolmap threads (-1 = all cores; 1 for repeatable runs)
    seed: int = 0  # random seed for pycolmap's RANSAC


def _progress(msg: str) -> None:
    print(f"[sfm mapping] {msg}", file=sys.stderr, flush=True)


def map_image_folder(images_dir: str | Path, work_dir: str | Path,
                     config: Optional[MappingConfig] = None,
                     camera: Optional[CameraIntrinsics] = None,
                     max_step_ratio: float = 5.0) -> tuple[Capture, SfmCloud, dict]:
    """Reconstruct the photos in ``images_dir`` without poses.

    ``camera``: calibrated intrinsics shared by all photos (e.g. from CameraInfo); they are
    then held fixed instead of estimated from a focal-length guess. ``max_step_ratio``: a
    camera path step above this x the median step is a jump (see ``path_jump``; it triggers the
    sequential re-match after exhaustive matching).

    Writes ``work_dir/database.db`` and ``work_dir/sparse/<k>`` (and
    ``work_dir/sparse_sequential/<k>`` after a re-match) and returns (Capture with the
    registered views and estimated poses, SfmCloud, stats with times per step).
    """
    import pycolmap

    cfg = config or MappingConfig()
    images_dir = Path(images_dir)
    work_dir = Path(work_dir)
    if not images_dir.is_dir():
        raise InputError(f"{images_dir} is not an image folder")
    from ..capture_io import IMAGE_SUFFIXES, _image_files  # the photos the reader takes
    names = [p.name for p in _image_files(images_dir)]
    if len(names) < 2:
        raise InputError(f"{images_dir} holds {len(names)} images; SfM needs at least 2 "
                         f"overlapping photos ({'/'.join(IMAGE_SUFFIXES)}, any case)")
    work_dir.mkdir(parents=True, exist_ok=True)
    db = work_dir / "database.db"
    if db.exists():
        db.unlink()
    pycolmap.set_random_seed(cfg.seed)
    stats: dict = {"images": len(names), "times_s": {}}

    t0 = time.perf_counter()
    _progress(f"extracting SIFT from {len(names)} images")
    ext = pycolmap.FeatureExtractionOptions()
    ext.max_image_size = cfg.max_image_size
    ext.num_threads = cfg.num_threads
    ext.use_gpu = False
    ext.sift.max_num_features = cfg.max_num_features
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "OPENCV"
    if camera is not None:
        from .export import camera_to_colmap
        camera.validate()
        model_id, params = camera_to_colmap(camera)
        reader.camera_model = {1: "PINHOLE", 4: "OPENCV", 5: "OPENCV_FISHEYE",
                               6: "FULL_OPENCV"}[model_id]
        reader.camera_params = ",".join(f"{p:.10g}" for p in params)
    groups = _size_groups(images_dir, names)
    if len(groups) > 1 and camera is None:
        # one shared camera drops every photo of another size (pycolmap logs a line and goes
        # on): portrait and landscape photos mixed, or two cameras -- one camera per size
        # then (pycolmap's AUTO mode gives every photo its own camera without EXIF focal
        # lengths, which registered 2 of 16 small photos)
        stats["cameras"] = {f"{w}x{h}": len(g) for (w, h), g in groups.items()}
        _progress("photos of {} sizes ({}): one camera per size".format(
            len(groups), ", ".join(f"{len(g)} at {w}x{h}" for (w, h), g in groups.items())))
    else:
        groups = {None: names}
    for group in groups.values():  # each call makes one camera for its photos
        pycolmap.extract_features(db, images_dir, image_names=group,
                                  camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=ext,
                                  device=pycolmap.Device.cpu)
    stats["times_s"]["features"] = time.perf_counter() - t0

    mode = "exhaustive" if len(names) <= cfg.exhaustive_max_images else "sequential"
    stats["matching"] = mode
    _match(db, cfg, mode, stats)
    result = _map(db, images_dir, work_dir / "sparse", cfg, camera, stats)
    if mode == "exhaustive" and cfg.sequential_rematch:
        first = _model_check(result[0], max_step_ratio)
        if first["path_step_ratio"] > max_step_ratio or first["looking_away"]:
            why = (f"camera path jump {first['path_step_ratio']:.1f}x the median step"
                   if first["path_step_ratio"] > max_step_ratio else
                   f"{len(first['looking_away'])} camera(s) looking away from the others' "
                   "convergence point")
            _progress(f"{why}: matching the photos sequentially too")
            again: dict = {"images": len(names), "times_s": {}}
            try:  # the exhaustive model is loaded: a failure here only loses the retry
                db2 = pycolmap.Database.open(str(db))
                try:
                    db2.clear_matches()
                    db2.clear_two_view_geometries()
                finally:
                    db2.close()
                _match(db, cfg, "sequential", again)
                other = _map(db, images_dir, work_dir / "sparse_sequential", cfg, camera, again)
            except Exception as exc:  # pycolmap raises its own types
                LOG.warning("sequential re-match failed (%s); keeping the exhaustive model", exc)
                other = None
            second = _model_check(other[0], max_step_ratio) if other is not None else None
            keep_other = second is not None and second["score"] > first["score"]
            stats["rematch"] = {"reason": why, "exhaustive": first, "sequential": second,
                                "kept": "sequential" if keep_other else "exhaustive"}
            for k, v in again["times_s"].items():
                stats["times_s"][f"{k}_rematch"] = v
            if keep_other:
                result = other
                stats["matching"] = f"sequential (after exhaustive: {why})"
                for k in ("models", "registered_images", "points", "mean_track_length",
                          "mean_reprojection_error_px"):
                    stats[k] = again[k]
            _progress(f"kept the {stats['rematch']['kept']} model")
    capture, cloud = result
    return capture, cloud, stats


def _size_groups(images_dir: Path, names: list[str]) -> dict:
    """{(width, height): [photo names of that size]}, largest group first, from the file
    headers (EXIF rotation is ignored, as pycolmap ignores it). Unreadable files join the
    first group (pycolmap reports them itself)."""
    from PIL import Image
    groups: dict = {}
    bad = []
    for n in names:
        try:
            with Image.open(images_dir / n) as im:
                groups.setdefault(im.size, []).append(n)
        except OSError:
            bad.append(n)
    groups = dict(sorted(groups.items(), key=lambda kv: -len(kv[1])))
    if bad:
        if not groups:
            return {None: bad}
        first = next(iter(groups))
        groups[first] = sorted(groups[first] + bad)
    return groups


def _match(db: Path, cfg: MappingConfig, mode: str, stats: dict) -> None:
    import pycolmap
    t0 = time.perf_counter()
    mopt = pycolmap.FeatureMatchingOptions()
    mopt.num_threads = cfg.num_threads
    mopt.use_gpu = False
    if mode == "exhaustive":
        _progress("exhaustive matching")
        pycolmap.match_exhaustive(db, matching_options=mopt, device=pycolmap.Device.cpu)
    else:
        _progress(f"sequential matching (overlap {cfg.sequential_overlap})")
        popt = pycolmap.SequentialPairingOptions()
        popt.overlap = cfg.sequential_overlap
        popt.quadratic_overlap = cfg.quadratic_overlap
        pycolmap.match_sequential(db, matching_options=mopt, pairing_options=popt,
                                  device=pycolmap.Device.cpu)
    stats["times_s"]["matching"] = time.perf_counter() - t0


def _map(db: Path, images_dir: Path, sparse: Path, cfg: MappingConfig,
         camera: Optional[CameraIntrinsics], stats: dict) -> tuple[Capture, SfmCloud]:
    """Incremental mapping of the matched database into ``sparse``; the largest model."""
    import pycolmap
    t0 = time.perf_counter()
    _progress("incremental mapping")
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = cfg.num_threads
    if camera is not None:
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
    sparse.mkdir(exist_ok=True)
    recs = pycolmap.incremental_mapping(db, images_dir, sparse, options=opts)
    stats["times_s"]["mapping"] = time.perf_counter() - t0
    if not recs:
        raise InputError(f"no reconstruction from {images_dir}: the photos do not overlap "
                         "enough or lack texture (check the folder holds one scene in order)")
    best_id = max(recs, key=lambda k: recs[k].num_reg_images())
    best = recs[best_id]
    stats["models"] = len(recs)
    stats["registered_images"] = int(best.num_reg_images())
    stats["points"] = int(best.num_points3D())
    stats["mean_track_length"] = float(best.compute_mean_track_length())
    stats["mean_reprojection_error_px"] = float(best.compute_mean_reprojection_error())
    model_dir = sparse / str(best_id)
    capture, cloud = load_colmap_model(model_dir, images_dir)
    capture.meta["sfm_model_dir"] = str(model_dir)
    _progress(f"registered {stats['registered_images']}/{stats['images']} images, "
              f"{stats['points']} points")
    return capture, cloud


def _model_check(capture: Capture, max_step_ratio: float) -> dict:
    """What the re-match compares: the path's largest step, the cameras looking away, and a
    score -- first whether the path steps evenly, then how many registered cameras have the
    convergence point in view (a camera registered in the wrong place loses it; a model
    with fewer photos registered loses them)."""
    ratio = path_jump(capture)[0]
    away = looking_away(capture)
    return {"registered_images": len(capture.views), "path_step_ratio": ratio,
            "looking_away": away,
            "score": [int(ratio <= max_step_ratio), len(capture.views) - len(away)]}


def looking_away(capture: Capture) -> list[str]:
    """Keys of the posed views whose image does not hold the point the cameras' optical axes
    converge on (behind the camera or outside the frame). The cameras of an orbit all
    frame it: the real bonsai's 289 (reference model), the simulator's captures and the demo
    bag have none, 0.16 of the distance off-axis at most; pose-free models of 37-59 of the
    bonsai's photos put the cameras they misplaced 0.44-0.62 off-axis or worse (2, 10 and
    42-55 of them looking away). Close-ups of parts of a large object may look away too:
    this is a reason to look, not proof of a fault."""
    from ..core.geometry import cameras_convergence_point
    views = [v for v in capture.views if v.pose is not None]
    if len(views) < 4:
        return []
    p = cameras_convergence_point([v.pose for v in views])
    out = []
    for v in views:
        x = v.pose.R.T @ (p - v.pose.t)
        cam = v.camera
        if x[2] <= 0:
            out.append(v.key)
            continue
        u = cam.fx * x[0] / x[2] + cam.cx
        w = cam.fy * x[1] / x[2] + cam.cy
        if not (-0.5 <= u < cam.width - 0.5 and -0.5 <= w < cam.height - 0.5):
            out.append(v.key)
    return out


def path_jump(capture: Capture) -> tuple[float, Optional[str]]:
    """The largest step between the camera centres of consecutive views (in key order, i.e.
    photo-name order), over the median step, and the key of the view it lands on. An orbit or
    a sweep photographed in order moves by similar steps (the real bonsai's reference model:
    at most 2.6x, across three missing photos); a block of photos the mapping put in the wrong
    place shows as steps of 8-13x at its ends (58 of its photos, session 16)."""
    views = sorted((v for v in capture.views if v.pose is not None), key=lambda v: v.key)
    if len(views) < 4:
        return 0.0, None
    c = np.stack([v.pose.t for v in views])
    step = np.linalg.norm(np.diff(c, axis=0), axis=1)
    med = float(np.median(step))
    if med <= 0:
        return 0.0, None
    i = int(np.argmax(step))
    return float(step[i] / med), views[i + 1].key
