"""Mask metrics against ground truth: IoU, precision, recall, Dice per view and per scene."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.types import InputError


def mask_metrics(pred: np.ndarray, gt: np.ndarray) -> dict:
    """IoU, precision, recall and Dice of one bool mask pair (empty-vs-empty counts as 1)."""
    pred, gt = np.asarray(pred, bool), np.asarray(gt, bool)
    if pred.shape != gt.shape:
        raise InputError(f"mask shapes differ: predicted {pred.shape} vs ground truth {gt.shape}")
    tp = float(np.logical_and(pred, gt).sum())
    fp = float(np.logical_and(pred, ~gt).sum())
    fn = float(np.logical_and(~pred, gt).sum())
    iou = tp / (tp + fp + fn) if tp + fp + fn else 1.0
    prec = tp / (tp + fp) if tp + fp else (1.0 if fn == 0 else 0.0)
    rec = tp / (tp + fn) if tp + fn else 1.0
    dice = 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else 1.0
    return {"iou": iou, "precision": prec, "recall": rec, "dice": dice}


def scene_metrics(pred: dict[str, np.ndarray], gt: dict[str, np.ndarray]) -> dict:
    """Per-view metrics and their means over views present in both dicts."""
    keys = [k for k in gt if k in pred]
    if not keys:
        raise InputError("no view key is shared by the predicted and ground-truth masks")
    per = {k: mask_metrics(pred[k], gt[k]) for k in keys}
    mean = {m: float(np.mean([p[m] for p in per.values()]))
            for m in ("iou", "precision", "recall", "dice")}
    return {"mean": mean, "per_view": per, "views": len(keys),
            "missing_predictions": sorted(set(gt) - set(pred))}


def load_mask_dir(path: str | Path) -> dict[str, np.ndarray]:
    """{stem: bool mask} from a folder of PNGs (pixels > 127 are object)."""
    from PIL import Image
    p = Path(path)
    if not p.is_dir():
        raise InputError(f"{p} is not a folder of mask PNGs")
    out = {}
    for f in sorted(p.glob("*.png")):
        a = np.asarray(Image.open(f).convert("L"))
        out[f.stem] = a > 127
    if not out:
        raise InputError(f"{p} holds no .png masks")
    return out


def format_table(result: dict) -> str:
    """Text table of a scene_metrics result."""
    lines = [f"{'view':>24} {'IoU':>6} {'prec':>6} {'recall':>6} {'Dice':>6}"]
    for k, m in result["per_view"].items():
        lines.append(f"{k:>24} {m['iou']:6.3f} {m['precision']:6.3f} {m['recall']:6.3f} "
                     f"{m['dice']:6.3f}")
    m = result["mean"]
    lines.append(f"{'MEAN':>24} {m['iou']:6.3f} {m['precision']:6.3f} {m['recall']:6.3f} "
                 f"{m['dice']:6.3f}")
    return "\n".join(lines)
