"""SfM with unknown poses: pycolmap incremental mapping over an image folder.

Used when a capture comes without poses (a plain image folder, a hand-held photo set). Features
are SIFT (pycolmap), pairs are sequential (photos taken in order along a path) for large sets and
exhaustive for small ones, and the largest reconstructed model is returned as a ``Capture``
with the estimated camera-to-world poses plus its ``SfmCloud``.
"""

from __future__ import annotations

import logging
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from ..core.types import CameraIntrinsics, Capture, InputError, SfmCloud
from .colmap_io import load_colmap_model

LOG = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".JPG", ".JPEG", ".PNG")


@dataclass
class MappingConfig:
    """Options of the unknown-pose mapping route."""

    max_image_size: int = 1600  # SIFT runs on images resized so the long side is at most this
    max_num_features: int = 8192  # SIFT features kept per image
    exhaustive_max_images: int = 60  # match every pair up to this many images, else sequential
    sequential_overlap: int = 12  # sequential matching: neighbours matched on each side
    quadratic_overlap: bool = True  # sequential matching: also match at 2^k offsets
    num_threads: int = -1  # pycolmap threads (-1 = all cores; 1 for repeatable runs)
    seed: int = 0  # random seed for pycolmap's RANSAC


def _progress(msg: str) -> None:
    print(f"[sfm mapping] {msg}", file=sys.stderr, flush=True)


def map_image_folder(images_dir: str | Path, work_dir: str | Path,
                     config: Optional[MappingConfig] = None,
                     camera: Optional[CameraIntrinsics] = None) -> tuple[Capture, SfmCloud, dict]:
    """Reconstruct the photos in ``images_dir`` without poses.

    ``camera``: calibrated intrinsics shared by all photos (e.g. from CameraInfo); they are
    then held fixed instead of estimated from a focal-length guess.

    Writes ``work_dir/database.db`` and ``work_dir/sparse/<k>`` and returns (Capture with the
    registered views and estimated poses, SfmCloud, stats with times per step).
    """
    import pycolmap

    cfg = config or MappingConfig()
    images_dir = Path(images_dir)
    work_dir = Path(work_dir)
    if not images_dir.is_dir():
        raise InputError(f"{images_dir} is not an image folder")
    names = sorted(p.name for p in images_dir.iterdir() if p.suffix in IMAGE_SUFFIXES)
    if len(names) < 2:
        raise InputError(f"{images_dir} holds {len(names)} images; SfM needs at least 2 "
                         "overlapping photos (.jpg/.png)")
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
    pycolmap.extract_features(db, images_dir, image_names=names,
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=ext, device=pycolmap.Device.cpu)
    stats["times_s"]["features"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    mopt = pycolmap.FeatureMatchingOptions()
    mopt.num_threads = cfg.num_threads
    mopt.use_gpu = False
    if len(names) <= cfg.exhaustive_max_images:
        _progress("exhaustive matching")
        stats["matching"] = "exhaustive"
        pycolmap.match_exhaustive(db, matching_options=mopt, device=pycolmap.Device.cpu)
    else:
        _progress(f"sequential matching (overlap {cfg.sequential_overlap})")
        stats["matching"] = "sequential"
        popt = pycolmap.SequentialPairingOptions()
        popt.overlap = cfg.sequential_overlap
        popt.quadratic_overlap = cfg.quadratic_overlap
        pycolmap.match_sequential(db, matching_options=mopt, pairing_options=popt,
                                  device=pycolmap.Device.cpu)
    stats["times_s"]["matching"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    _progress("incremental mapping")
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = cfg.num_threads
    if camera is not None:
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
    sparse = work_dir / "sparse"
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
    _progress(f"registered {stats['registered_images']}/{len(names)} images, "
              f"{stats['points']} points")
    return capture, cloud, stats
