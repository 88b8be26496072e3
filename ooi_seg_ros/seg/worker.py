"""``segment`` in a worker process, for a node that shares its own process with other work.

A full segmentation run is thousands of short numpy / scipy / OpenCV calls. Inside a ROS
node's process it competes for the GIL with the executor's callbacks and whatever else lives
there (in the load benchmark: the SfM node and a 30 Hz 1280x720 camera publisher), and was
measured ~10x slower per mask than the same run alone (BENCHMARKS.md, Nodes, session 7). In a
``core.worker.SubprocessWorker`` it gets a GIL, and on a 2-core machine a core, of its own.

The worker keeps the keyframe images it was sent, keyed by stamp: each run sends only the
images it has not seen (a keyframe whose image object changed is sent again) and the list of
stamps alive, so a run costs the new keyframes' pixels, not all of them. The results are the
same as ``segment`` in the calling process (the same function on the same inputs; tested).
The worker's image cache doubles the memory of the kept keyframe images (bounded by the
node's ``image_budget_mb``).
"""

from __future__ import annotations

import dataclasses
from typing import Collection, Optional

import numpy as np

from ..core.types import Capture, SfmCloud, View
from ..core.worker import SubprocessWorker
from .pipeline import SegmentationConfig, SegmentationResult, segment


class _PointsDone(Exception):
    pass


def _raise_points(ooi: SfmCloud) -> None:
    raise _PointsDone(ooi)


def point_stages(capture: Capture, cloud: SfmCloud, cfg: SegmentationConfig) -> SfmCloud:
    """The OOI cloud of ``segment`` (its point stages only: no mesh, masks or refinement)."""
    try:
        segment(capture, cloud, cfg, on_cloud=_raise_points)
    except _PointsDone as done:
        return done.args[0]
    raise RuntimeError("segment returned without reaching its point stages")


def _segment_job(state: dict, job: tuple):
    """Worker handler: ("points" | "full", views, cloud, cfg, mask_keys, new_images, alive,
    context masks bit-packed {key: (bits, shape)} or None)."""
    kind, views, cloud, cfg, mask_keys, new_images, alive, ctx_bits = job
    ctx = None if ctx_bits is None else {
        k: np.unpackbits(b, count=int(np.prod(shape))).reshape(shape).astype(bool)
        for k, (b, shape) in ctx_bits.items()}
    cache = state.setdefault("images", {})
    for s in [s for s in cache if s not in alive]:
        del cache[s]
    cache.update(new_images)
    for v in views:
        v.image = cache[v.stamp_ns]
    capture = Capture(views=views, source="ros")
    try:
        if kind == "points":
            ooi = point_stages(capture, cloud, cfg)
            return np.asarray(ooi.xyz), np.asarray(ooi.rgb)
        return segment(capture, cloud, cfg, mask_keys=mask_keys, context_masks=ctx)
    finally:
        for v in views:  # the result refers to them: send no pixels back
            v.image = None


class SegmentationWorker:
    """``segment`` / ``point_stages`` of a node's keyframes in a worker process (see module)."""

    def __init__(self, nice: int = 0) -> None:
        self._w = SubprocessWorker(f"{__name__}:_segment_job", None, name="segmentation",
                                   nice=nice)
        self._sent: dict[int, np.ndarray] = {}  # stamp -> the image object the worker holds

    @property
    def alive(self) -> bool:
        return self._w.alive

    @property
    def pid(self) -> int:
        return self._w.pid

    @property
    def nice(self) -> int:
        """How far below the caller's CPU priority the worker runs (0 if lowering failed)."""
        return self._w.nice

    def _job(self, kind: str, views: list[View], cloud: SfmCloud, cfg: SegmentationConfig,
             mask_keys: Optional[Collection[str]], context_masks: Optional[dict] = None):
        light = {id(v): dataclasses.replace(v, image=None, loader=None) for v in views}
        for v in cloud.views:
            if id(v) not in light:
                light[id(v)] = dataclasses.replace(v, image=None, loader=None)
        lviews = [light[id(v)] for v in views]
        lcloud = dataclasses.replace(cloud, views=[light[id(v)] for v in cloud.views])
        alive = {v.stamp_ns for v in views}
        new = {}
        for v in views:
            img = v.get_image()
            if self._sent.get(v.stamp_ns) is not img:
                new[v.stamp_ns] = img
        try:
            ctx = None if context_masks is None else {
                k: (np.packbits(np.asarray(m, bool)), np.shape(m))
                for k, m in context_masks.items()}
            out = self._w.submit((kind, lviews, lcloud, cfg,
                                  None if mask_keys is None else list(mask_keys), new,
                                  alive, ctx)).result()
        except BaseException:
            self._sent.clear()  # unknown what the worker holds now: resend everything
            raise
        self._sent = {s: img for s, img in self._sent.items() if s in alive}
        for s in new:
            self._sent[s] = new[s]
        return out

    def point_stages(self, views: list[View], cloud: SfmCloud, cfg: SegmentationConfig
                     ) -> tuple[np.ndarray, np.ndarray]:
        """(xyz, rgb) of the OOI cloud."""
        return self._job("points", views, cloud, cfg, None)

    def segment(self, views: list[View], cloud: SfmCloud, cfg: SegmentationConfig,
                mask_keys: Optional[Collection[str]] = None,
                context_masks: Optional[dict] = None) -> SegmentationResult:
        """``segment`` (``mask_keys``, ``context_masks`` as there) in the worker."""
        return self._job("full", views, cloud, cfg, mask_keys, context_masks)

    def close(self, timeout: float = 10.0) -> None:
        self._w.close(timeout)
