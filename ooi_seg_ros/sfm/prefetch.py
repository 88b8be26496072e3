"""Pipelined known-pose SfM: keyframe k+1's SIFT runs in a worker process while k is matched.

On the CPU a keyframe's cost is SIFT extraction plus matching + triangulation, and the two are
independent across keyframes: extraction needs only the image, matching needs the features of
the earlier keyframes. With the extraction of the next keyframes on a second core, a stream is
processed at max(extraction, matching + triangulation) per keyframe instead of their sum.

A worker *process*, not a thread: pycolmap's ``Sift.extract`` holds the GIL (two threads
extracting at once took twice the wall time of one, measured with pycolmap 4.2.1; see
BENCHMARKS.md), so a thread would only interleave with the matching. The worker gets the RGB
keyframe image and returns keypoints, quantised descriptors and colours
(``KeyframeFeatures``), computed by the same function the serial path runs: the cloud is
bit-identical to ``IncrementalSfM.add_keyframe(view)`` alone. At most ``ahead`` keyframes are
in flight, so memory stays bounded (one image and one feature set each).

The worker is a ``core.worker.SubprocessWorker`` (a ``python -c`` subprocess, not a
``multiprocessing`` child: see there). If the worker dies, the keyframes in flight are
extracted in the calling thread and the pipeline carries on serially (counted as
``feature_worker_failures``).
"""

from __future__ import annotations

import collections
import logging
import time
from concurrent.futures import Future
from typing import Iterable, Iterator, Optional

from ..core.types import View
from ..core.worker import SubprocessWorker, WorkerDied, usable_cores
from .incremental import (IncrementalConfig, IncrementalSfM, KeyframeFeatures,
                          _check_view, extract_features, make_sift, sift_first_octave)

LOG = logging.getLogger(__name__)


def _extract_job(state: dict, job: tuple) -> KeyframeFeatures:
    """Worker handler: (image, camera, key) -> features, one SIFT extractor per first octave
    kept in the worker's ``state`` (``state["init"]`` = the ``IncrementalConfig``)."""
    img, cam, key = job
    cfg = state["init"]
    octave = sift_first_octave(cfg, cam.width, cam.height)
    sift = state.setdefault("sift", {})
    if octave not in sift:
        sift[octave] = make_sift(cfg, octave)
    return extract_features(sift[octave], img, cam, key, octave)


class FeatureWorker(SubprocessWorker):
    """A subprocess extracting ``KeyframeFeatures`` in submission order (``submit`` returns a
    ``Future``)."""

    def __init__(self, config: IncrementalConfig):
        super().__init__(f"{__name__}:_extract_job", config, name="sfm-feature")

    def submit(self, img, cam, key: str) -> Future:  # type: ignore[override]
        return super().submit((img, cam, key))


def default_feature_workers() -> int:
    """1 where the process may use 2+ CPU cores (pipelining pays), else 0 (serial)."""
    return 1 if usable_cores() >= 2 else 0


class PipelinedSfM:
    """``IncrementalSfM`` fed through a feature-extraction worker process, keyframes in order.

    Use ``run(views)`` for a whole sequence, or for a live stream ``submit(view)`` as
    keyframes arrive (while ``can_submit``) and ``add_next()`` to add the oldest one to the
    SfM (it waits for its features). ``workers=0`` extracts in the calling thread: the same
    interface, the serial path; None picks 1 where 2+ cores are usable. ``keep_images=False``
    drops each keyframe's image once its features are in the SfM.

    It pays where a second core is free (on two free cores 1.6-1.8x the serial keyframe rate at
    640x480); where the process gets less than one core in all, the two processes share it and
    nothing is gained (a few percent more CPU per keyframe; see BENCHMARKS.md).
    """

    def __init__(self, sfm: Optional[IncrementalSfM] = None, ahead: int = 2,
                 workers: Optional[int] = None, keep_images: bool = True):
        if ahead < 1:
            raise ValueError(f"ahead must be >= 1 (keyframes extracted ahead), got {ahead}")
        self.sfm = sfm if sfm is not None else IncrementalSfM()
        self.ahead = int(ahead)
        self.keep_images = keep_images  # False: a keyframe's pixels are let go once it is added
        self.workers = default_feature_workers() if workers is None else int(workers)
        self._pending: collections.deque = collections.deque()  # (view, Future or None)
        self._worker: Optional[FeatureWorker] = None
        if self.workers > 0:
            try:
                self._worker = FeatureWorker(self.sfm.config)
            except OSError as exc:  # no interpreter to start, no processes left
                self._fail_over(exc)

    def _fail_over(self, exc: BaseException) -> None:
        """The worker died: continue serially (counted, logged)."""
        self.sfm.counts["feature_worker_failures"] += 1
        LOG.warning("SfM feature worker failed (%s); extracting in this thread from now on",
                    exc)
        if self._worker is not None:
            self._worker.close(timeout=1.0)
        self._worker = None
        self.workers = 0

    # -- stream interface --------------------------------------------------------------------
    @property
    def pending(self) -> int:
        """Keyframes submitted and not yet added to the SfM."""
        return len(self._pending)

    @property
    def next_key(self) -> Optional[str]:
        """Key of the keyframe ``add_next`` adds next (None when none is in flight)."""
        return self._pending[0][0].key if self._pending else None

    @property
    def can_submit(self) -> bool:
        """True while fewer than ``ahead`` keyframes are in flight."""
        return len(self._pending) < self.ahead

    def submit(self, view: View) -> None:
        """Starts extracting ``view``'s features (returns at once); add it with ``add_next``.

        Raises ``InputError`` for a view SfM cannot use (no intrinsics or pose, bad pose) and
        ``RuntimeError`` when ``ahead`` keyframes are in flight already (call ``add_next``).
        """
        if not self.can_submit:
            raise RuntimeError(f"{self.ahead} keyframes in flight already: add_next() first")
        _check_view(view)
        fut: Optional[Future] = None
        if self._worker is not None:
            try:
                fut = self._worker.submit(view.get_image(), view.camera, view.key)
            except WorkerDied as exc:
                self._fail_over(exc)
        self._pending.append((view, fut))

    def add_next(self) -> dict:
        """Adds the oldest submitted keyframe to the SfM; returns ``add_keyframe``'s stats.

        Waits for its features; an ``InputError`` of that keyframe (e.g. an image that does
        not match its camera_info) is raised here, after it left the pipeline.
        """
        if not self._pending:
            raise RuntimeError("no keyframe submitted")
        view, fut = self._pending.popleft()
        features: Optional[KeyframeFeatures] = None
        t0 = time.perf_counter()
        try:
            if fut is not None:
                try:
                    features = fut.result()
                except WorkerDied as exc:
                    self._fail_over(exc)
                    for i, (v, _) in enumerate(self._pending):  # lost with the worker: redo
                        self._pending[i] = (v, None)
            wait_s = time.perf_counter() - t0
            stats = self.sfm.add_keyframe(view, features)
        finally:
            if not self.keep_images:  # the features are all SfM needs (a live node's memory)
                view.image = None
        stats["features_wait_s"] = wait_s
        stats["features_cpu_s"] = features.extract_cpu_s if features is not None else None
        return stats

    def run(self, views: Iterable[View]) -> Iterator[dict]:
        """Adds ``views`` in order, extraction running ``ahead`` keyframes in front; yields
        each keyframe's stats after it was added (the SfM may be queried in between)."""
        it = iter(views)
        done = False
        while True:
            while not done and self.can_submit:
                try:
                    self.submit(next(it))
                except StopIteration:
                    done = True
            if not self._pending:
                return
            yield self.add_next()

    # -- the wrapped SfM ---------------------------------------------------------------------
    def cloud(self, conditioned: Optional[bool] = None):
        """The SfM's current cloud (keyframes still in flight are not in it)."""
        return self.sfm.cloud(conditioned)

    def report(self) -> dict:
        rep = self.sfm.report()
        rep["feature_workers"] = self.workers
        return rep

    def close(self) -> None:
        """Stops the worker; keyframes still in flight are discarded."""
        self._pending.clear()
        if self._worker is not None:
            self._worker.close()
            self._worker = None

    def __enter__(self) -> "PipelinedSfM":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
