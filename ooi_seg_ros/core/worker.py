"""A Python subprocess that runs one handler function on pickled jobs (stdin -> stdout).

Two kinds of work in this package must leave the calling process to use a second core: SIFT
extraction (``sfm.prefetch``: pycolmap holds the GIL) and a node's full segmentation run
(``seg.worker``: a run is thousands of short numpy / scipy / OpenCV calls, and inside a node's
process it shares the GIL with the executor, the SfM node and, in the load benchmark, the
camera publisher -- measured ~10x slower there than alone).

The worker is a plain ``python -c`` subprocess speaking pickle over its stdin/stdout, not a
``multiprocessing`` child: ``spawn`` and ``forkserver`` re-import the caller's main script
(running an unguarded script a second time), and ``fork`` is unsafe in a process with threads
such as a ROS node. The first message names the handler (``"module:function"``) and its
initial value; every job then becomes ``handler(state, job)`` in the worker, where ``state``
is a dict that lives as long as the worker (``state["init"]`` = the initial value) -- a
cache the caller may rely on only while the worker lives. Results come back in submission
order as ``Future``s; an exception raised by the handler is re-raised by the Future, and a
worker that dies fails every pending Future with ``WorkerDied`` (the caller decides whether to
carry on in its own thread).
"""

from __future__ import annotations

import importlib
import os
import pickle
import queue
import subprocess
import sys
import threading
from concurrent.futures import Future
from pathlib import Path
from typing import Any, Optional


def _serve() -> None:
    """The worker's main loop: (handler, init) first, then (id, job) until EOF or None."""
    import signal
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's; it closes our stdin
    out = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # a library printing to stdout must not corrupt the protocol
    inp = sys.stdin.buffer
    handler_path, init = pickle.load(inp)
    module, name = handler_path.split(":")
    handler = getattr(importlib.import_module(module), name)
    state: dict = {"init": init}
    while True:
        try:
            msg = pickle.load(inp)
        except EOFError:
            return
        if msg is None:
            return
        jid, job = msg
        try:
            res = (jid, True, handler(state, job))
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
    """The worker process ended or its pipe broke."""


class SubprocessWorker:
    """A subprocess running ``handler`` (``"module:function"``) on jobs in submission order
    (``submit`` returns a ``Future``). Writing jobs and reading results run on two small I/O
    threads, so neither ``submit`` nor the worker waits for the other. ``nice`` > 0 lowers the
    worker's CPU priority by that much (``self.nice`` says whether it took)."""

    def __init__(self, handler: str, init: Any = None, name: str = "worker",
                 env: Optional[dict] = None, nice: int = 0):
        import ooi_seg_ros
        root = str(Path(ooi_seg_ros.__file__).resolve().parents[1])
        penv = dict(os.environ)
        penv["PYTHONPATH"] = os.pathsep.join([root] + [p for p in [penv.get("PYTHONPATH")] if p])
        penv.setdefault("OMP_NUM_THREADS", "1")
        penv.update(env or {})
        self.name = name
        self.proc = subprocess.Popen(
            [sys.executable, "-c", f"from {__name__} import _serve; _serve()"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=penv)
        self.nice = 0
        if nice > 0:
            # set from here (no preexec_fn: unsafe in a process with threads, such as a node);
            # the worker's first job waits in its stdin, so nothing runs at the old priority
            try:
                cur = os.getpriority(os.PRIO_PROCESS, self.proc.pid)
                os.setpriority(os.PRIO_PROCESS, self.proc.pid, min(19, cur + int(nice)))
                self.nice = int(nice)
            except (OSError, AttributeError):  # not permitted / not POSIX: run at our priority
                pass
        self._lock = threading.Lock()
        self._futures: dict[int, Future] = {}
        self._next_id = 0
        self._dead: Optional[str] = None
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._jobs.put((handler, init))
        self._writer = threading.Thread(target=self._write_loop, daemon=True,
                                        name=f"{name}-writer")
        self._reader = threading.Thread(target=self._read_loop, daemon=True,
                                        name=f"{name}-reader")
        self._writer.start()
        self._reader.start()

    @property
    def alive(self) -> bool:
        return self._dead is None

    @property
    def pid(self) -> int:
        return self.proc.pid

    def submit(self, job: Any) -> Future:
        """Queues one job; the Future raises ``WorkerDied`` if the worker goes."""
        fut: Future = Future()
        with self._lock:
            if self._dead is not None:
                raise WorkerDied(self._dead)
            jid = self._next_id
            self._next_id += 1
            self._futures[jid] = fut
        self._jobs.put((jid, job))
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
            self._fail_all(f"cannot write to the {self.name} process: {exc}")
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
                self._fail_all(f"{self.name} process ended (exit code {code}): {exc!r}")
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
        self._fail_all(f"{self.name} process closed")


def usable_cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1
