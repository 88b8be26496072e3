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

The worker is a plain ``python -c`` subprocess speaking pickle over its stdin/stdout, not a
``multiprocessing`` child: ``spawn`` and ``forkserver`` re-import the caller's main script
(running an unguarded script a second time), and ``fork`` is unsafe in a process with threads
such as a ROS node. If the worker dies, the keyframes in flight are extracted in the calling
thread and the pipeline carries on serially (counted as ``feature_worker_failures``).
"""

from __future__ import annotations

import collections
import logging
import os
import pickle
import queue
import subprocess
import sys
import threading
import time
from concurrent.futures import Future
from pathlib import Path
from typing import Iterable, Iterator, Optional

from ..core.types import View
from .incremental import (IncrementalConfig, IncrementalSfM, KeyframeFeatures,
                          _check_view, extract_features, make_sift, sift_first_octave)

LOG = logging.getLogger(__name__)

# in the worker process: its config and one SIFT extractor per first octave
_WORKER: dict = {}


def _worker_extract(img, cam, key: str) -> KeyframeFeatures:
    cfg = _WORKER["config"]
    octave = sift_first_octave(cfg, cam.width, cam.height)
    sift = _WORKER.setdefault("sift", {})
    if octave not in sift:
        sift[octave] = make_sift(cfg, octave)
    return extract_features(sift[octave], img, cam, key, octave)


def _serve() -> None:
    """The worker's main loop: config first, then (id, image, camera, key) jobs until EOF."""
    import signal
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's; it closes our stdin
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # a library printing to stdout must not corrupt the protocol
    inp = sys.stdin.buffer
    _WORKER["config"] = pickle.load(inp)
    import pycolmap  # noqa: F401  (loaded before the first keyframe arrives)
    while True:
        try:
            job = pickle.load(inp)
        except EOFError:
            return
        if job is None:
            return
        jid, img, cam, key = job
        try:
            res = (jid, True, _worker_extract(img, cam, key))
        except Exception as exc:  # noqa: BLE001 — handed to the caller, who decides
            try:
                pickle.dumps(exc)
            except Exception:  # noqa: BLE001 — an exception that does not pickle
                exc = RuntimeError(repr(exc))
            res = (jid, False, exc)
        try:
            pickle.dump(res, out, protocol=pickle.HIGHEST_PROTOCOL)
            out.flush()
        except OSError:  # the parent has gone
            return


class WorkerDied(RuntimeError):
    """The feature worker process ended or its pipe broke."""


class FeatureWorker:
    """A subprocess extracting ``KeyframeFeatures`` in submission order (``submit`` returns a
    ``Future``). Writing images and reading results run on two small I/O threads, so neither
    ``submit`` nor the worker waits for the other."""

    def __init__(self, config: IncrementalConfig):
        import ooi_seg_ros
        root = str(Path(ooi_seg_ros.__file__).resolve().parents[1])
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([root] + [p for p in [env.get("PYTHONPATH")] if p])
        env.setdefault("OMP_NUM_THREADS", "1")
        self.proc = subprocess.Popen(
            [sys.executable, "-c", f"from {__name__} import _serve; _serve()"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
        self._lock = threading.Lock()
        self._futures: dict[int, Future] = {}
        self._next_id = 0
        self._dead: Optional[str] = None
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._jobs.put(config)
        self._writer = threading.Thread(target=self._write_loop, daemon=True,
                                        name="sfm-feature-writer")
        self._reader = threading.Thread(target=self._read_loop, daemon=True,
                                        name="sfm-feature-reader")
        self._writer.start()
        self._reader.start()

    @property
    def alive(self) -> bool:
        return self._dead is None

    def submit(self, img, cam, key: str) -> Future:
        """Queues one extraction; the Future raises ``WorkerDied`` if the worker goes."""
        fut: Future = Future()
        with self._lock:
            if self._dead is not None:
                raise WorkerDied(self._dead)
            jid = self._next_id
            self._next_id += 1
            self._futures[jid] = fut
        self._jobs.put((jid, img, cam, key))
        return fut

    def _fail_all(self, why: str) -> None:
        with self._lock:
            if self._dead is None:
                self._dead = why
            futs, self._futures = list(self._futures.values()), {}
        for f in futs:
            if not f.done():
                f.set_exception(WorkerDied(why))

    def _write_loop(self) -> None:
        try:
            while True:
                job = self._jobs.get()
                if job is None:
                    break
                pickle.dump(job, self.proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
                self.proc.stdin.flush()
        except (OSError, ValueError) as exc:  # broken pipe / closed file: the worker is gone
            self._fail_all(f"cannot write to the feature worker: {exc}")
            return
        try:
            self.proc.stdin.close()
        except OSError:
            pass

    def _read_loop(self) -> None:
        while True:
            try:
                jid, ok, value = pickle.load(self.proc.stdout)
            except (EOFError, OSError, pickle.UnpicklingError, ValueError) as exc:
                code = self.proc.poll()
                self._fail_all(f"feature worker ended (exit code {code}): {exc!r}")
                return
            with self._lock:
                fut = self._futures.pop(jid, None)
            if fut is None:
                continue
            if ok:
                fut.set_result(value)
            else:
                fut.set_exception(value)

    def close(self, timeout: float = 10.0) -> None:
        """Ends the worker (after the jobs already queued); kills it if it does not go."""
        self._jobs.put(None)
        try:
            self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self._writer.join(timeout=1.0)
        self._reader.join(timeout=1.0)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self._fail_all("feature worker closed")


def default_feature_workers() -> int:
    """1 where the process may use 2+ CPU cores (pipelining pays), else 0 (serial)."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    return 1 if n >= 2 else 0


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
