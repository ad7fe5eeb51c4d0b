"""Clocks of robots at their own pace: this robot's capture-stamp clock, and its peers' offsets from it.

A capture stamp is a time of the robot's camera clock (a live camera's driver), or of a dataset (a
replay, a bag). :class:`StampClock` says what that clock reads *now*: a recent frame's stamp moved
on by the wall time since it arrived, at the rate stamps advance against wall time (1 for a live
camera; a bag played at ``--rate`` advances that much slower); of the recent frames, the one that
says latest (an arrival noted late, by a busy process, only makes its reading early). Every frame a robot sends carries
its clock's reading; a peer takes ``sender's reading - own reading on arrival`` as a sample of the
offset between the two clocks (less the travel time), and :class:`PeerOffsets` keeps the largest
of the samples of the last ``OFFSET_MAX_AGE_S`` (the one that travelled fastest). An offset within ``tolerance_s`` is taken
as none (synchronised clocks stay as they are); beyond it, the peer's stamps are mapped into this
robot's clock, and the first time is reported (``link:clock-offset``).
"""
from __future__ import annotations

import threading
import time
from collections import deque

#: frames whose (stamp, arrival) a :class:`StampClock` keeps to estimate its rate
RATE_WINDOW = 32
#: the rate is estimated only over frames spanning at least this wall time (s); 1 before
RATE_MIN_SPAN_S = 1.0
#: offset samples a :class:`PeerOffsets` keeps per peer, and for how long (s of wall time)
OFFSET_WINDOW = 64
OFFSET_MAX_AGE_S = 10.0


class StampClock:
    """This robot's capture-stamp clock, from its frames' ``(stamp, wall arrival)`` (thread-safe)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._seen: deque[tuple[float, float]] = deque(maxlen=RATE_WINDOW)

    def note(self, stamp_s: float, arrival_s: float) -> None:
        """A frame stamped ``stamp_s`` arrived at wall time ``arrival_s`` (``time.time()``)."""
        with self._lock:
            if self._seen and stamp_s < self._seen[-1][0]:
                self._seen.clear()  # the stamps went back: another clock from now on
            self._seen.append((float(stamp_s), float(arrival_s)))

    def rate(self) -> float:
        """Stamp seconds per wall second over the recent frames (1 until they span ``RATE_MIN_SPAN_S``)."""
        with self._lock:
            if len(self._seen) < 2:
                return 1.0
            (s0, w0), (s1, w1) = self._seen[0], self._seen[-1]
        if w1 - w0 < RATE_MIN_SPAN_S or s1 <= s0:
            return 1.0
        return min(max((s1 - s0) / (w1 - w0), 0.01), 100.0)

    def now(self, wall_s: float | None = None) -> float | None:
        """The stamp clock's reading at wall time ``wall_s`` (now); None before the first frame."""
        rate = self.rate()
        wall = time.time() if wall_s is None else wall_s
        with self._lock:
            if not self._seen:
                return None
            return max(s + (wall - w) * rate for s, w in self._seen)


class PeerOffsets:
    """Each peer's clock offset from this robot's (``peer - mine``, seconds), from arrival samples."""

    def __init__(self, tolerance_s: float) -> None:
        self.tolerance_s = float(tolerance_s)
        self._samples: dict[str, deque[tuple[float, float]]] = {}

    def sample(self, peer: str, peer_clock_s: float, my_clock_s: float | None) -> None:
        if my_clock_s is None or not peer_clock_s == peer_clock_s:  # NaN: the peer had no frame yet
            return
        got = self._samples.setdefault(peer, deque(maxlen=OFFSET_WINDOW))
        got.append((time.monotonic(), float(peer_clock_s) - float(my_clock_s)))

    def estimate(self, peer: str) -> float | None:
        """The offset estimate (largest recent sample), None without samples."""
        got = self._samples.get(peer)
        if not got:
            return None
        young = [v for t, v in got if time.monotonic() - t <= OFFSET_MAX_AGE_S]
        return max(young) if young else got[-1][1]

    def offset(self, peer: str) -> float:
        """The offset applied to ``peer``'s stamps: the estimate beyond ``tolerance_s``, else 0."""
        est = self.estimate(peer)
        return est if est is not None and abs(est) > self.tolerance_s else 0.0

    def reset(self, peer: str) -> None:
        self._samples.pop(peer, None)
