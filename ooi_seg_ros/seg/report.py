"""Writing a segmentation result to a folder: PLYs, mask PNGs, JSON/YAML and an HTML report."""

from __future__ import annotations

import base64
import html
import io
import json
from pathlib import Path
from typing import Optional

import numpy as np

from ..core import config as cfgmod
from ..core.geometry import look_at
from ..core.types import CameraIntrinsics, Capture, InputError
from .pipeline import SegmentationResult


def render_points(xyz: np.ndarray, rgb: np.ndarray, cam: CameraIntrinsics, pose) -> np.ndarray:
    """Splat points into an image [H,W,3] uint8 with a painter's z-order (far first)."""
    from ..core.geometry import project
    img = np.full((cam.height, cam.width, 3), 255, np.uint8)
    if len(xyz) == 0:
        return img
    uv, z = project(xyz, cam, pose)
    u, v = np.rint(uv[:, 0]).astype(int), np.rint(uv[:, 1]).astype(int)
    ok = (z > 0) & (u >= 1) & (u < cam.width - 1) & (v >= 1) & (v < cam.height - 1)
    order = np.argsort(-z[ok])
    u, v, c = u[ok][order], v[ok][order], np.asarray(rgb)[ok][order]
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            img[v + dy, u + dx] = c
    return img


def stage_renders(result: SegmentationResult, capture: Capture, size: int = 360) -> dict:
    """Each stage's cloud rendered from one fixed viewpoint that frames the final OOI cloud."""
    xyz0 = result.ooi_cloud.xyz if len(result.ooi_cloud) else result.stage_clouds["input"][0]
    target = np.asarray(result.params["orbit"]["convergence_point"])
    pose0 = capture.views[0].pose
    d = pose0.t - target
    lo, hi = np.percentile(xyz0, 2, axis=0), np.percentile(xyz0, 98, axis=0)
    dist = 2.5 * max(np.linalg.norm(hi - lo) / 2, 1e-6) / np.tan(np.radians(30))
    up = -pose0.R[:, 1]
    eye = target + d / max(np.linalg.norm(d), 1e-12) * dist
    pose = look_at(eye, target, up)
    cam = CameraIntrinsics(size, size * 3 // 4, size / (2 * np.tan(np.radians(30))),
                           size / (2 * np.tan(np.radians(30))), size / 2, size * 3 / 8)
    return {k: render_points(x, c, cam, pose) for k, (x, c) in result.stage_clouds.items()}


def overlay(img: np.ndarray, mask: np.ndarray, gt: Optional[np.ndarray] = None) -> np.ndarray:
    """Image with the background dimmed and the mask outline in green (GT outline in blue)."""
    from scipy import ndimage
    o = img.astype(float)
    o[~mask] *= 0.35
    edge = mask & ~ndimage.binary_erosion(mask, iterations=2)
    o[edge] = [0, 255, 0]
    if gt is not None:
        ge = gt & ~ndimage.binary_erosion(gt, iterations=1)
        o[ge] = [40, 80, 255]
    return o.astype(np.uint8)


def _png64(a: np.ndarray) -> str:
    from PIL import Image
    buf = io.BytesIO()
    Image.fromarray(a).save(buf, format="PNG")
    return base64.b64encode(buf.getvalue()).decode()


def _to_o3d_cloud(xyz: np.ndarray, rgb: np.ndarray):
    import open3d as o3d
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(xyz, float)))
    if len(rgb):
        pc.colors = o3d.utility.Vector3dVector(np.asarray(rgb, float) / 255.0)
    return pc


def report_dict(result: SegmentationResult) -> dict:
    """The JSON-able summary written as report.json."""
    met = None
    if result.metrics is not None:
        met = {"mean": result.metrics["mean"], "views": result.metrics["views"],
               "per_view": result.metrics["per_view"]}
    return {"method": result.config.method, "counts": result.counts, "params": result.params,
            "timings_s": {k: round(v, 4) for k, v in result.timings.items()},
            "warnings": result.warnings, "metrics": met,
            "mask_coverage_mean": float(np.mean([m.mean() for m in result.masks.values()]))}


def write_outputs(out: str | Path, result: SegmentationResult, capture: Capture,
                  input_info: dict, n_overlays: int = 8, photos: Optional[dict] = None,
                  photo_gt: Optional[dict] = None) -> Path:
    """Write every output of ``ooi-seg segment`` into ``out`` and return the folder.

    ``photos``: the views at their photos' size by key (images loaded on demand), when the
    run worked at a smaller size: each mask is written at its photo's size, its outline
    placed by the photo (``masks.mask_at_size`` with the photo as guide), so that a mask
    matches the photo it is named after. ``photo_gt``: ground-truth masks at the photos'
    size; the metrics are then taken from the written masks, as ``ooi-seg eval`` takes them
    (``input_info["metrics_size"] = "photo"``)."""
    import open3d as o3d
    from PIL import Image

    from .masks import mask_at_size
    from .metrics import mask_metrics
    out = Path(out)
    try:
        (out / "masks").mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create output folder {out}: {exc}") from None
    o3d.io.write_point_cloud(str(out / "ooi_points.ply"),
                             _to_o3d_cloud(result.ooi_cloud.xyz, result.ooi_cloud.rgb))
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(result.mesh.vertices),
                                  o3d.utility.Vector3iVector(result.mesh.triangles))
    o3d.io.write_triangle_mesh(str(out / "ooi_mesh.ply"), m)
    per_view: dict = {}
    unguided: list[str] = []
    for v in capture.views:
        mask = result.masks[v.key]
        pv = (photos or {}).get(v.key)
        size = (pv.camera.width, pv.camera.height) if pv is not None else None
        if size is not None and size != (v.camera.width, v.camera.height):
            try:
                guide = pv.get_image()
            except InputError:  # read once already; gone since: enlarged without it
                guide = None
                unguided.append(v.key)
            mask = mask_at_size(mask, size, guide=guide)
        if photo_gt is not None and v.key in photo_gt:
            per_view[v.key] = mask_metrics(mask, photo_gt[v.key])
        Image.fromarray(mask.astype(np.uint8) * 255).save(out / "masks" / f"{v.key}.png")
    if unguided:
        result.warnings.append(f"masks: {len(unguided)} photo(s) could not be read again to "
                               f"place the enlarged outline ({', '.join(unguided[:5])})")
    if per_view and result.metrics is not None:
        result.metrics = {"mean": {k: float(np.mean([p[k] for p in per_view.values()]))
                                   for k in ("iou", "precision", "recall", "dice")},
                          "per_view": per_view, "views": len(per_view),
                          "missing_predictions": sorted(set(photo_gt) - set(per_view))}
        input_info["metrics_size"] = "photo"
    rep = report_dict(result)
    (out / "report.json").write_text(json.dumps(rep, indent=1))
    cfgmod.write_yaml(result.config, out / "config.yaml")
    (out / "input.json").write_text(json.dumps(input_info, indent=1))
    write_html(out / "report.html", result, capture, rep, n_overlays)
    return out


def write_html(path: Path, result: SegmentationResult, capture: Capture, rep: dict,
               n_overlays: int) -> None:
    """Self-contained HTML report: stage renders, mask overlays, counts, metrics, warnings."""
    parts = [f"<html><head><meta charset='utf-8'><title>ooi-seg report</title></head><body>"
             f"<h1>Segmentation report ({html.escape(result.config.method)})</h1>"]
    if result.warnings:
        parts.append("<h2>Warnings</h2><ul>" + "".join(
            f"<li>{html.escape(w)}</li>" for w in result.warnings) + "</ul>")
    parts.append("<h2>Points after each stage</h2><table border=1><tr><th>stage</th>"
                 "<th>points</th><th>time [s]</th></tr>")
    for k, n in result.counts.items():
        t = result.timings.get(k)
        parts.append(f"<tr><td>{k}</td><td>{n}</td><td>{'' if t is None else f'{t:.2f}'}"
                     f"</td></tr>")
    parts.append("</table><div>")
    for k, img in stage_renders(result, capture).items():
        parts.append(f"<figure style='display:inline-block'><img src='data:image/png;base64,"
                     f"{_png64(img)}'><figcaption>{k}</figcaption></figure>")
    parts.append("</div><h2>Masks (green: mask outline; blue: ground truth)</h2><div>")
    views = capture.views
    step = max(1, len(views) // n_overlays)
    for v in views[::step][:n_overlays]:
        o = overlay(v.get_image(), result.masks[v.key], v.gt_mask)
        parts.append(f"<figure style='display:inline-block'><img width=320 "
                     f"src='data:image/png;base64,{_png64(o)}'><figcaption>"
                     f"{html.escape(v.key)}</figcaption></figure>")
    parts.append("</div>")
    if result.metrics is not None:
        mm = result.metrics["mean"]
        parts.append("<h2>Metrics (mean over views)</h2><table border=1><tr>" + "".join(
            f"<th>{k}</th>" for k in mm) + "</tr><tr>" + "".join(
            f"<td>{v:.3f}</td>" for v in mm.values()) + "</tr></table>")
    parts.append("<h2>Parameters used</h2><pre>" + html.escape(
        json.dumps(rep["params"], indent=1)[:20000]) + "</pre></body></html>")
    path.write_text("".join(parts))
