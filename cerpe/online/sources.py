"""Where a robot's frames come from online: a replay of a dataset, or its ROS 2 topics (:mod:`cerpe.online.ros_input`).

A source yields :class:`Frame`\\ s when the robot is ready for one, always its newest: what came while
the robot was busy and was overtaken by a newer frame is dropped and counted on the frame taken
(``input:frame-dropped``), a gap longer than the stall time too (``input:stall``). Its ``clock``
(``now()``) is the robot's capture-stamp clock (:mod:`cerpe.online.clock`).

:class:`ManifestReplay` plays one robot of a manifest encounter against the wall clock at ``speed``
(1: real time; 0: every frame, as fast as the robot computes), from the team's replay time when
peers are running already (a robot that joins late starts where they are).
"""
from __future__ import annotations

import threading
import time
from collections import Counter
from typing import Any, Iterator, NamedTuple, Sequence

import numpy as np

from ..protocols import FrameContext


class Frame(NamedTuple):
    """One frame for the robot: its pixels, context, capture stamp (s), wall arrival (``time.time()``), the
    robot's own odometry pose ``T_odom_cam`` at it (None: none) and what its input counted."""

    image: np.ndarray
    context: FrameContext
    stamp_s: float
    arrival_s: float
    T_odom_cam: np.ndarray | None = None
    degradations: tuple[str, ...] = ()


class StallWatch:
    """Counts ``input:stall`` once for a gap of more than ``stall_s`` between the stamps of two frames taken."""

    def __init__(self, stall_s: float) -> None:
        self.stall_s = float(stall_s)
        self.last: float | None = None
        self.n_stalls = 0

    def check(self, stamp_s: float) -> list[str]:
        last, self.last = self.last, float(stamp_s)
        if last is not None and self.stall_s > 0 and stamp_s - last > self.stall_s:
            self.n_stalls += 1
            return ["input:stall"]
        return []


class ReplayClock:
    """The capture-stamp clock of a replay: ``stamp = start_stamp + (wall - start_wall) * speed``."""

    def __init__(self, start_stamp_s: float, speed: float) -> None:
        self.start_stamp_s, self.speed, self.start_wall = float(start_stamp_s), float(speed), time.time()
        self.last_stamp_s = float(start_stamp_s)  # speed 0: the clock is the last frame's stamp

    def now(self, wall_s: float | None = None) -> float:
        if self.speed <= 0:
            return self.last_stamp_s
        return self.start_stamp_s + ((time.time() if wall_s is None else wall_s) - self.start_wall) * self.speed

    def wall_of(self, stamp_s: float) -> float:
        return self.start_wall + (float(stamp_s) - self.start_stamp_s) / self.speed


class ManifestReplay:
    """Robot ``robot_id``'s frames of a manifest encounter, by the encounter's stamps.

    Args:
        stream: its :class:`~cerpe.scene.RobotStream`.
        speed: replay speed against the stamps (1: real time; 0: every frame, no waiting, none dropped).
        seed: the frames' random seed (simulated depth sources draw from it).
        odometry: ``[T,4,4]`` the robot's own ``T_odom_cam`` per frame (NaN rows: none) to use instead of
            the backbone's ego-motion (``--use-odometry``), or None.
        stall_s: a gap between frames taken longer than this is counted (0: never).
    """

    def __init__(self, stream: Any, speed: float = 1.0, seed: int = 0, odometry: Sequence | None = None,
                 stall_s: float = 2.0) -> None:
        self.stream, self.speed, self.seed = stream, float(speed), int(seed)
        self.odometry = None if odometry is None else np.asarray(odometry, dtype=np.float64)
        self.stamps = np.asarray(stream.stamps_s, dtype=np.float64)
        self.clock = ReplayClock(float(self.stamps[0]), self.speed)
        self.stalls = StallWatch(stall_s)
        self.n_dropped = 0
        self.first = 0
        self._stop = threading.Event()

    @property
    def stats(self) -> Counter[str]:
        return Counter({"input:frame-dropped": self.n_dropped, "input:stall": self.stalls.n_stalls})

    def stop(self) -> None:
        """End :meth:`frames` after the frame in progress."""
        self._stop.set()

    def start(self, team_stamp_s: float | None = None) -> None:
        """Start the replay now, at the team's replay time when peers run already (else at the first frame)."""
        start = float(self.stamps[0]) if team_stamp_s is None else max(float(self.stamps[0]), float(team_stamp_s))
        self.first = int(np.searchsorted(self.stamps, start - 1e-9))
        self.clock = ReplayClock(start, self.speed)

    def _frame(self, t: int, arrival_s: float, dropped: int) -> Frame:
        s = self.stream
        X = None
        if self.odometry is not None:
            X = self.odometry[t] if np.all(np.isfinite(self.odometry[t])) else np.full((4, 4), np.nan)
        degr = ("input:frame-dropped",) * dropped + tuple(self.stalls.check(float(self.stamps[t])))
        return Frame(s.image(t), FrameContext(s.robot_id, t, s.intrinsics, s.depth_m(t), self.seed),
                     float(self.stamps[t]), arrival_s, X, degr)

    def frames(self) -> Iterator[Frame]:
        t, n = self.first, len(self.stamps)
        while t < n and not self._stop.is_set():
            if self.speed <= 0:
                self.clock.last_stamp_s = float(self.stamps[t])
                yield self._frame(t, time.time(), 0)
                t += 1
                continue
            now = self.clock.now()
            newest = int(np.searchsorted(self.stamps, now, side="right")) - 1
            if newest < t:  # the next frame is not due yet
                self._stop.wait(max(0.0, self.clock.wall_of(self.stamps[t]) - time.time()))
                continue
            self.n_dropped += newest - t
            yield self._frame(newest, self.clock.wall_of(self.stamps[newest]), newest - t)
            t = newest + 1
