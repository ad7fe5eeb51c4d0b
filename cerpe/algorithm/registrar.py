"""Registering received images apart from the ego-motion step: the seam between a robot's step and a worker.

Synchronously (:class:`~cerpe.algorithm.team.Team`, ``cerpe run``) a robot has no registrar: its one
joint pass holds its own views and the received images, and every direct estimate lands at the step it
was requested for (Algorithm 1 as written). With a registrar the step's pass holds the robot's own views
only (the ego-motion keeps its rate); the joint pass over own views and received images becomes a
:class:`RegistrationJob`, run by a worker, and its estimates land when it is done. The robot then brings
them to its current frame through both robots' odometry, as propagation does
(:meth:`cerpe.algorithm.agent.RobotAgent.collect_registrations`).

A :class:`Registrar` takes jobs and hands back results; it never blocks a step:

* :meth:`Registrar.submit` queues a job; a full queue drops its OLDEST job (returned, so the robot counts it);
* :meth:`Registrar.landed` returns the results finished since the last call (never waits);
* :meth:`Registrar.stats` counts jobs submitted, done, failed, dropped, lost and worker restarts, and the
  worker's CPU seconds (measured apart from the step's).

:class:`WorkerRegistrar` runs the jobs on a worker thread, oldest first, at a lower priority, with the
interpreter switching threads more often (:data:`WORKER_SWITCH_S`). A job whose pass raises is a
failed result (counted); a worker that dies (an exception that escapes its loop) loses the job it ran
(counted ``lost``) and is started again on the next call (counted ``restarts``).
"""
from __future__ import annotations

import logging
import os
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Protocol, Sequence

from ..protocols import BackboneOutput, PoseBackbone, View

log = logging.getLogger(__name__)

#: jobs waiting for the worker at most; one more drops the oldest (a robot submits one job per step, so
#: a worker slower than the camera falls at most this many steps behind before estimates are skipped)
QUEUE_SIZE = 2
#: how much nicer the worker thread runs than the step's (Linux; 0: the same): on cores both need, the
#: kernel favours the step, and the worker still gets a share (at the nicest, +19, a saturated robot's
#: worker lands few registrations and drops the rest)
WORKER_NICE = 10
#: the interpreter's thread switch interval while a worker runs, seconds (Python's default is 0.005): a
#: step that wants the GIL back from the worker, between two numpy or torch calls, waits up to this long
#: each time. The kernel's priority cannot help there: the GIL is Python's
WORKER_SWITCH_S = 0.0005


@dataclass
class RegistrationJob:
    """The joint pass of one step: ``views`` as :meth:`~cerpe.protocols.PoseBackbone.infer` takes them
    (own views first, the received images last); ``step`` the step it was requested at."""

    step: int
    views: Sequence[View]
    submitted_s: float = field(default_factory=time.perf_counter)


@dataclass
class RegistrationResult:
    """The finished job: the pass's output (None when it failed, ``error`` then says why), the worker's
    CPU and wall seconds on it, and when it finished (``perf_counter``)."""

    step: int
    out: BackboneOutput | None
    error: str = ""
    cpu_s: float = 0.0
    wall_s: float = 0.0
    submitted_s: float = 0.0
    finished_s: float = 0.0


class Registrar(Protocol):
    """What a robot needs of a registration worker (see the module docstring)."""

    def submit(self, job: RegistrationJob) -> list[RegistrationJob]:
        """Queue ``job``; returns the jobs dropped to make room (oldest first)."""
        ...

    def landed(self) -> list[RegistrationResult]:
        """Results finished since the last call, in the order they finished (never blocks)."""
        ...

    def stats(self) -> dict[str, float]:
        ...

    def close(self) -> None:
        ...


class WorkerRegistrar:
    """A :class:`Registrar` whose jobs a worker thread runs through ``backbone.infer``.

    Args:
        backbone: the pose backbone (may be the robot's own: the offline backbone's caches are
            thread-safe and a cache hit equals a recomputation).
        queue_size: jobs waiting at most (:data:`QUEUE_SIZE`).
    """

    def __init__(self, backbone: PoseBackbone, queue_size: int = QUEUE_SIZE) -> None:
        self.backbone = backbone
        self.queue_size = max(int(queue_size), 1)
        self._cond = threading.Condition()
        self._queue: deque[RegistrationJob] = deque()
        self._done: list[RegistrationResult] = []
        self._running: RegistrationJob | None = None
        self._thread: threading.Thread | None = None
        self._closed = False
        self.counts: dict[str, float] = {"submitted": 0, "done": 0, "failed": 0, "dropped": 0, "lost": 0,
                                         "restarts": 0, "worker_cpu_s": 0.0, "worker_wall_s": 0.0}

    # ---------------------------------------------------------------- the robot's side
    def submit(self, job: RegistrationJob) -> list[RegistrationJob]:
        dropped: list[RegistrationJob] = []
        with self._cond:
            if self._closed:
                raise RuntimeError("registrar: closed")
            self._ensure_worker()
            while len(self._queue) >= self.queue_size:
                dropped.append(self._queue.popleft())
            self._queue.append(job)
            self.counts["submitted"] += 1
            self.counts["dropped"] += len(dropped)
            self._cond.notify_all()
        for d in dropped:
            log.debug("registrar: queue full, dropped the job of step %d", d.step)
        return dropped

    def landed(self) -> list[RegistrationResult]:
        with self._cond:
            self._ensure_worker()
            out, self._done = self._done, []
        return out

    def pending(self) -> int:
        """Jobs queued or running."""
        with self._cond:
            return len(self._queue) + (self._running is not None)

    def wait(self, timeout_s: float | None = None) -> bool:
        """Block until no job is queued or running (a live worker needed; restarted if dead); whether it got there."""
        end = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            while self._queue or self._running is not None:
                self._ensure_worker()
                left = None if end is None else end - time.monotonic()
                if left is not None and left <= 0:
                    return False
                self._cond.wait(0.05 if left is None else min(left, 0.05))
            return True

    def stats(self) -> dict[str, float]:
        with self._cond:
            return dict(self.counts)

    def close(self) -> None:
        """Stop the worker after the job it runs; queued jobs are dropped (not counted)."""
        with self._cond:
            self._closed = True
            self._queue.clear()
            self._cond.notify_all()
            thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=60)

    # ---------------------------------------------------------------- the worker's side
    def _ensure_worker(self) -> None:
        """Start the worker (again, counted, when it died). Call with the lock held."""
        if self._thread is not None and self._thread.is_alive():
            return
        if self._thread is not None:  # it died: the job it ran is lost
            self.counts["restarts"] += 1
            if self._running is not None:
                self.counts["lost"] += 1
                self._running = None
            log.warning("registrar: the registration worker died; started again")
        self._thread = threading.Thread(target=self._loop, name="cerpe-registrar", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        lower_priority(WORKER_NICE)
        if sys.getswitchinterval() > WORKER_SWITCH_S:  # process-wide, and left so: the next worker wants it too
            sys.setswitchinterval(WORKER_SWITCH_S)
        while True:
            with self._cond:
                while not self._queue and not self._closed:
                    self._cond.wait()
                if self._closed:
                    return
                job = self._running = self._queue.popleft()
            res = self._run(job)
            with self._cond:
                self._running = None
                self._done.append(res)
                self.counts["done" if res.out is not None else "failed"] += 1
                self.counts["worker_cpu_s"] += res.cpu_s
                self.counts["worker_wall_s"] += res.wall_s
                self._cond.notify_all()

    def _run(self, job: RegistrationJob) -> RegistrationResult:
        w, c = time.perf_counter(), time.thread_time()
        try:
            out, error = self.backbone.infer(list(job.views)), ""
        except Exception as exc:  # noqa: BLE001 - a failed job is a counted result, never a dead robot
            out, error = None, f"{type(exc).__name__}: {exc}"
            log.warning("registrar: the registration of step %d failed: %s", job.step, error)
        return RegistrationResult(step=job.step, out=out, error=error, cpu_s=time.thread_time() - c,
                                  wall_s=time.perf_counter() - w, submitted_s=job.submitted_s,
                                  finished_s=time.perf_counter())


def lower_priority(nice: int) -> bool:
    """Make the calling thread ``nice`` steps nicer (Linux: a thread's niceness is its own); whether it took."""
    if nice <= 0 or not hasattr(os, "setpriority") or not hasattr(threading, "get_native_id"):
        return False
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, min(os.getpriority(os.PRIO_PROCESS, tid) + int(nice), 19))
    except OSError:
        return False
    return True


def merge_stats(stats: Sequence[dict[str, Any]]) -> dict[str, float]:
    """The sum of several registrars' :meth:`~Registrar.stats`."""
    out: dict[str, float] = {}
    for s in stats:
        for k, v in s.items():
            out[k] = out.get(k, 0) + v
    return out
