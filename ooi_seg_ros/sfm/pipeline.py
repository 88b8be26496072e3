"""SfM over a whole ``Capture``: keyframes -> incremental known-pose SfM, or mapping without poses.

``reconstruct`` is what ``ooi-seg sfm`` and ``ooi-seg segment`` (via ``sfm.run_sfm``) call.
"""

from __future__ import annotations

import logging
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from ..core.geometry import cameras_convergence_point
from ..core.types import Capture, InputError, SfmCloud
from .incremental import IncrementalConfig, IncrementalSfM
from .keyframes import KeyframeConfig, KeyframeSelector
from .mapping import MappingConfig, looking_away, map_image_folder, path_jump  # noqa: F401
from .prefetch import PipelinedSfM

LOG = logging.getLogger(__name__)


@dataclass
class SfmConfig:
    """The SfM stage: keyframe selection, incremental SfM, optional BA, unknown-pose mapping."""

    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)  # keyframe selection
    incremental: IncrementalConfig = field(default_factory=IncrementalConfig)  # known poses
    mapping: MappingConfig = field(default_factory=MappingConfig)  # unknown poses
    use_all_frames: bool = False  # skip keyframe selection (a photo set is all keyframes)
    bundle_adjust: bool = False  # refine the points with pycolmap BA (poses fixed)
    refine_poses: bool = False  # with bundle_adjust: refine the keyframe poses too
    progress: bool = True  # print a progress bar on stderr
    feature_workers: int = -1  # processes extracting SIFT ahead of the matching (keyframe k+1
    # while k is matched; same cloud, ~max instead of sum of the two costs): 0 = serial,
    # -1 = 1 where 2+ CPU cores are usable, else 0
    features_ahead: int = 2  # keyframes extracted ahead at most (bounds the images in flight)
    max_path_step_ratio: float = 5.0  # unknown poses: warn when consecutive photos' estimated
    # cameras (name order) step more than this x the median step (a block registered in the
    # wrong place; see path_jump)


class Progress:
    """A plain-text progress bar on stderr (no dependency)."""

    def __init__(self, label: str, total: int, enabled: bool = True, width: int = 30):
        self.label, self.total, self.enabled, self.width = label, max(total, 1), enabled, width
        self.t0 = time.perf_counter()

    def update(self, done: int, extra: str = "") -> None:
        if not self.enabled:
            return
        f = min(done / self.total, 1.0)
        bar = "#" * int(f * self.width) + "-" * (self.width - int(f * self.width))
        el = time.perf_counter() - self.t0
        end = "\n" if done >= self.total else ""
        print(f"\r{self.label} [{bar}] {done}/{self.total} {el:6.1f}s {extra}", end=end,
              file=sys.stderr, flush=True)


def _scene_scale(capture: Capture) -> Optional[float]:
    poses = [v.pose for v in capture.views if v.pose is not None]
    if len(poses) < 3:
        return None
    c = cameras_convergence_point(poses)
    d = np.linalg.norm(np.stack([p.t for p in poses]) - c, axis=1)
    s = float(np.median(d))
    return s if np.isfinite(s) and s > 0 else None


def reconstruct(capture: Capture, config: Optional[SfmConfig] = None,
                work_dir: Optional[str | Path] = None,
                keep_model: Optional[str | Path] = None) -> tuple[Capture, SfmCloud, dict]:
    """(Capture of the keyframes with poses, SfmCloud, report) of ``capture``.

    Posed captures go through keyframe selection and the known-pose incremental SfM; captures
    without poses through pycolmap mapping of their image folder (``work_dir`` holds its
    database and model; ``keep_model``: a folder the chosen COLMAP model -- the estimated
    cameras and poses -- is copied to, e.g. for a later ``ooi-seg train``; model image names
    are the views' file names, whose stems are the view keys).
    """
    cfg = config or SfmConfig()
    if len(capture.views) < 2:
        raise InputError(f"capture {capture.source or ''} has {len(capture.views)} views; SfM "
                         "needs at least 2 overlapping images")
    report: dict = {"input_views": len(capture.views), "times_s": {}}
    if not capture.has_poses:
        return _reconstruct_unposed(capture, cfg, work_dir, report, keep_model)
    # keyframes
    t0 = time.perf_counter()
    sel = KeyframeSelector(cfg.keyframes)
    scale = _scene_scale(capture)
    if scale is not None:
        sel.set_scene_scale(scale)
    for v in capture.views:
        if v.camera is None:
            raise InputError(f"view {v.key} has no camera intrinsics (no CameraInfo); record "
                             "camera_info with the images")
        v.camera.validate()
    keyframes = []
    for v in capture.views:
        if cfg.use_all_frames:
            ok = v.pose is not None
        else:
            ok = sel.offer(v)
        if ok:
            keyframes.append(v)
    report["keyframe_selection"] = sel.report() if not cfg.use_all_frames else {
        "frames_seen": len(capture.views), "keyframes": len(keyframes), "dropped": {}}
    report["times_s"]["keyframes"] = time.perf_counter() - t0
    if len(keyframes) < 2:
        raise InputError(f"only {len(keyframes)} keyframe(s) selected from "
                         f"{len(capture.views)} frames (drops: {dict(sel.dropped)}); the camera "
                         "must move around the object (or lower keyframes.translation_frac)")
    sfm = IncrementalSfM(cfg.incremental, scene_scale=scale)
    bar = Progress("sfm keyframes", len(keyframes), cfg.progress)
    workers = None if cfg.feature_workers < 0 else cfg.feature_workers
    with PipelinedSfM(sfm, ahead=cfg.features_ahead, workers=workers) as pipe:
        for i, _ in enumerate(pipe.run(keyframes)):
            bar.update(i + 1)
    cloud = sfm.cloud()
    rep = pipe.report()
    report["incremental"] = rep
    report["times_s"].update(rep["times_s"])
    if len(cloud) == 0:
        raise InputError(f"SfM found no 3D points in {len(keyframes)} keyframes "
                         f"({rep['counts'].get('verified_matches', 0)} verified matches): the "
                         "images are textureless, out of focus or do not overlap")
    if cfg.bundle_adjust:
        from .ba import bundle_adjust
        t0 = time.perf_counter()
        cloud, report["bundle_adjustment"] = bundle_adjust(cloud, cfg.refine_poses)
        report["times_s"]["bundle_adjustment_s"] = time.perf_counter() - t0
    out_cap = Capture(views=list(cloud.views), source=capture.source,
                      gt_ooi_points=capture.gt_ooi_points, meta=dict(capture.meta))
    report.update(summarize(cloud))
    return out_cap, cloud, report


def _same_size_on_disk(capture: Capture) -> bool:
    """True when the first view's image file has the view's size (no --downscale)."""
    from PIL import Image
    v = capture.views[0]
    try:
        with Image.open(v.source) as im:
            return im.size == (v.camera.width, v.camera.height)
    except OSError:
        return False


def _any_turned(paths: list[Path]) -> bool:
    """True when a photo's EXIF Orientation turns it: pycolmap reads the stored pixels, the
    capture loads photos upright, so such photos are handed to pycolmap as upright copies."""
    from PIL import Image
    from ..capture_io import exif_orientation
    for p in paths:
        try:
            with Image.open(p) as im:
                if exif_orientation(im) != 1:
                    return True
        except OSError:
            continue
    return False


def _reconstruct_unposed(capture: Capture, cfg: SfmConfig, work_dir: Optional[str | Path],
                         report: dict, keep_model: Optional[str | Path] = None
                         ) -> tuple[Capture, SfmCloud, dict]:
    srcs = [Path(v.source) for v in capture.views if v.source]
    folders = {p.parent for p in srcs}
    tmp = None
    on_disk = (len(srcs) == len(capture.views) and len(folders) == 1
               and all(p.is_file() for p in srcs) and _same_size_on_disk(capture)
               and not _any_turned(srcs))
    if on_disk:  # the photos themselves (not downscaled copies): let pycolmap read them
        images_dir = folders.pop()
    else:  # write the images out for pycolmap (downscaled, or turned upright as loaded)
        from PIL import Image
        tmp = tempfile.TemporaryDirectory(prefix="sfm_images_")
        images_dir = Path(tmp.name)
        unreadable = []
        for v in capture.views:
            try:
                img = v.get_image()
            except InputError as exc:  # a photo whose header read but whose pixels do not
                unreadable.append(f"{v.key}: {exc}")
                continue
            Image.fromarray(img).save(images_dir / f"{v.key}.png")
        if unreadable:
            report["unreadable_images"] = unreadable
            if len(unreadable) == len(capture.views):
                tmp.cleanup()
                raise InputError(f"none of the {len(unreadable)} images can be read: "
                                 f"{'; '.join(unreadable[:3])}")
    own_work = work_dir is None  # a scratch folder of ours: removed when the mapping is read
    work = Path(tempfile.mkdtemp(prefix="sfm_map_")) if own_work else Path(work_dir)
    try:
        # intrinsics of images that came from a stream/dataset (CameraInfo) are calibrated
        cams = {(v.camera.width, v.camera.height, v.camera.fx, v.camera.fy, v.camera.cx,
                 v.camera.cy) for v in capture.views}
        calibrated = capture.views[0].camera if tmp is not None and len(cams) == 1 else None
        cap, cloud, stats = map_image_folder(images_dir, work, cfg.mapping, camera=calibrated,
                                             max_step_ratio=cfg.max_path_step_ratio)
        if tmp is not None:  # load the images before their temporary folder goes
            for v in cap.views:
                v.get_image()
        if keep_model is not None:
            keep = Path(keep_model)
            if keep.exists():
                shutil.rmtree(keep)
            shutil.copytree(cap.meta["sfm_model_dir"], keep)
            cap.meta["sfm_model_dir"] = str(keep)
        elif own_work:
            cap.meta.pop("sfm_model_dir", None)
    finally:
        if tmp is not None:
            tmp.cleanup()
        if own_work:
            shutil.rmtree(work, ignore_errors=True)
    report["mapping"] = stats
    msgs = []
    if stats["registered_images"] < 0.5 * len(capture.views):
        msgs.append(f"only {stats['registered_images']}/{len(capture.views)} images "
                    "registered; use larger images (less --downscale) or a capture with more "
                    "overlap")
    jump = path_jump(cap)
    report["camera_path_max_step_ratio"] = jump[0]
    if jump[0] > cfg.max_path_step_ratio:
        msgs.append(f"the estimated cameras jump along the photos' order: {jump[1]} is "
                    f"{jump[0]:.1f}x the median step from the photo before it; if the photos "
                    "were taken in name order along one path, part of the capture was "
                    "registered in the wrong place (its own reprojection error does not show "
                    "this) -- check the cameras in the SfM output, or add photos between")
    if report.get("unreadable_images"):
        bad = report["unreadable_images"]
        msgs.append(f"{len(bad)} image(s) could not be decoded and were left out of the "
                    f"mapping (no mask): {'; '.join(bad[:3])}")
    away = looking_away(cap)
    report["cameras_looking_away"] = away
    if away:
        msgs.append(f"{len(away)} of {len(cap.views)} estimated cameras do not have the point "
                    f"the cameras converge on in their image ({', '.join(away[:5])}"
                    f"{', ...' if len(away) > 5 else ''}); if those photos show the object, "
                    "the mapping registered them in the wrong place and their masks will be "
                    "wrong -- look at them, or add photos between")
    for msg in msgs:  # the CLI prints these once through its logging handler
        LOG.warning(msg)
    if msgs:
        report["warning"] = "; ".join(msgs)
    report["times_s"].update({f"{k}_s": v for k, v in stats["times_s"].items()})
    report["keyframe_selection"] = {"frames_seen": len(capture.views),
                                    "keyframes": stats["registered_images"],
                                    "dropped": {"not_registered": len(capture.views)
                                                - stats["registered_images"]}}
    report.update(summarize(cloud))
    return cap, cloud, report


def summarize(cloud: SfmCloud) -> dict:
    """Points, mean track length and median reprojection error of a cloud."""
    n = len(cloud)
    return {"points": n, "keyframes_used": len(cloud.views),
            "mean_track_length": float(np.mean(cloud.track_lengths())) if n else 0.0,
            "median_reprojection_px": float(np.median(cloud.error)) if n else 0.0}


def run_sfm(capture: Capture, config: Optional[SfmConfig] = None) -> SfmCloud:
    """The SfM cloud of ``capture`` (what the segmentation CLI calls without a cloud)."""
    return reconstruct(capture, config)[1]
