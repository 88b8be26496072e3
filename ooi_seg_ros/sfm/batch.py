"""Baseline: one-shot batch triangulation of all keyframes with pycolmap (point_triangulator).

COLMAP's own known-pose route: the keyframes are written as images, pycolmap extracts SIFT into
a database, matches (exhaustive for small sets, sequential otherwise) with its own geometric
verification, and ``pycolmap.triangulate_points`` triangulates and bundle-adjusts the points
with the poses held fixed. The incremental path is measured against this.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import numpy as np

from ..core.types import InputError, SfmCloud, View
from .colmap_io import load_colmap_model
from .export import camera_to_colmap, write_colmap_model


@dataclass
class BatchConfig:
    """Options of the batch pycolmap triangulation baseline."""

    max_features: int = 4096  # SIFT features per image
    exhaustive_max_images: int = 40  # match every pair up to this many images, else sequential
    sequential_overlap: int = 10  # sequential matching: neighbours on each side
    num_threads: int = 1  # pycolmap threads
    seed: int = 0  # pycolmap random seed


def batch_triangulate(views: list[View], config: Optional[BatchConfig] = None,
                      work_dir: Optional[str | Path] = None) -> tuple[SfmCloud, dict]:
    """Cloud over ``views`` (poses fixed) by pycolmap's point_triangulator, plus timings."""
    import pycolmap
    from PIL import Image

    cfg = config or BatchConfig()
    if len(views) < 2:
        raise InputError(f"batch triangulation needs at least 2 posed views, got {len(views)}")
    cams = {(v.camera.width, v.camera.height, v.camera.fx, v.camera.fy, v.camera.cx,
             v.camera.cy) for v in views}
    if len(cams) != 1 or views[0].camera.has_distortion:
        raise InputError("the batch baseline supports one undistorted camera for all views")
    own_tmp = work_dir is None
    work = Path(tempfile.mkdtemp(prefix="sfm_batch_")) if own_tmp else Path(work_dir)
    times: dict = {}
    try:
        img_dir = work / "images"
        img_dir.mkdir(parents=True, exist_ok=True)
        names = [f"{k:05d}.png" for k in range(len(views))]
        for n, v in zip(names, views):
            Image.fromarray(v.get_image()).save(img_dir / n)
        db = work / "database.db"
        if db.exists():
            db.unlink()
        pycolmap.set_random_seed(cfg.seed)
        t0 = time.perf_counter()
        model, params = camera_to_colmap(views[0].camera)
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        reader.camera_params = ",".join(f"{p:.10g}" for p in params)
        ext = pycolmap.FeatureExtractionOptions()
        ext.use_gpu = False
        ext.num_threads = cfg.num_threads
        ext.max_image_size = 100000
        ext.sift.max_num_features = cfg.max_features
        pycolmap.extract_features(db, img_dir, image_names=names,
                                  camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                                  extraction_options=ext, device=pycolmap.Device.cpu)
        times["features_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        mopt = pycolmap.FeatureMatchingOptions()
        mopt.use_gpu = False
        mopt.num_threads = cfg.num_threads
        if len(views) <= cfg.exhaustive_max_images:
            pycolmap.match_exhaustive(db, matching_options=mopt, device=pycolmap.Device.cpu)
        else:
            popt = pycolmap.SequentialPairingOptions()
            popt.overlap = cfg.sequential_overlap
            pycolmap.match_sequential(db, matching_options=mopt, pairing_options=popt,
                                      device=pycolmap.Device.cpu)
        times["matching_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        dbh = pycolmap.Database.open(str(db))
        by_name = {im.name: (im.image_id, im.camera_id) for im in dbh.read_all_images()}
        dbh.close()
        ids = [by_name[n][0] for n in names]
        empty = SfmCloud.empty(views)
        in_dir = work / "posed"
        write_colmap_model(empty, in_dir, views, image_ids=ids, names=names)
        rec = pycolmap.Reconstruction(str(in_dir))
        out_dir = work / "triangulated"
        out_dir.mkdir(exist_ok=True)
        opts = pycolmap.IncrementalPipelineOptions()
        opts.num_threads = cfg.num_threads
        rec = pycolmap.triangulate_points(rec, db, img_dir, out_dir, clear_points=True,
                                          options=opts)
        rec.write(str(out_dir))
        times["triangulation_s"] = time.perf_counter() - t0
        _, cloud = load_colmap_model(out_dir, img_dir)
        # load_colmap_model orders views by name = our order; point them at the caller's views
        cloud.views = list(views)
        stats = {"points": len(cloud), "times_s": times,
                 "mean_track_length": float(np.mean(cloud.track_lengths())) if len(cloud) else 0,
                 "median_reprojection_px": float(np.median(cloud.error)) if len(cloud) else 0}
        return cloud, stats
    finally:
        if own_tmp:
            shutil.rmtree(work, ignore_errors=True)
