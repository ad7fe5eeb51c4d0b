"""One robot of a team, online: its :class:`~cerpe.algorithm.StepEngine` over a :class:`TcpLink`.

The phases of a step are the engine's, the same as in :class:`~cerpe.algorithm.Team`;
this module adds what a robot process needs around them: waiting for the peers
before step 0, pacing the replay, and per-wait deadlines (``step_timeout_s``).
What is counted is listed in :mod:`cerpe.online.tcp_link`.
"""
from __future__ import annotations

import logging
import time
from collections import Counter
from typing import Any, Iterable, Iterator, Mapping, Sequence

import numpy as np

from ..algorithm import AlgorithmError, RobotAgent, StepEngine, drive
from ..protocols import FrameContext
from ..records import StepResult
from .net import NetTransport, OnlineError
from .tcp_link import TcpLink

log = logging.getLogger(__name__)

default_conf: dict[str, Any] = {
    "step_timeout_s": 5.0,      # longest wait for the peers' frames of the same step (descriptors, replies, poses)
    "connect_timeout_s": 30.0,  # before step 0: wait this long for every peer to connect
    "max_lag_steps": 2,         # do not wait for a peer this many steps behind (it cannot catch up)
    "max_ahead_steps": 64,      # frames further ahead than this are dropped (counted, ``too_far_ahead``)
    "rate_hz": 0.0,             # replay rate: step t starts no earlier than t / rate_hz after step 0; 0 = free
}


class RobotNode:
    """Runs one robot's agent against its peers on a :class:`~cerpe.online.net.NetTransport`.

    Args:
        agent: this robot's agent (its ``index`` is its wire sender id).
        robot_ids: every robot of the encounter in wire-index order (index = position).
        peers: the robots on the network (a subset of ``robot_ids``); pair records
            are made for these.
        transport: connected (or connecting) transport of this robot.
        conf: overrides of :data:`default_conf`.
    """

    def __init__(self, agent: RobotAgent, robot_ids: Sequence[str], peers: Iterable[str],
                 transport: NetTransport, conf: Mapping[str, Any] | None = None) -> None:
        unknown = set(conf or {}) - set(default_conf)
        if unknown:
            raise OnlineError(f"node conf: unknown keys {sorted(unknown)}; valid: {sorted(default_conf)}")
        self.conf = {**default_conf, **(conf or {})}
        self.agent, self.net = agent, transport
        self.link = TcpLink(transport, robot_ids, self.conf["max_lag_steps"], self.conf["max_ahead_steps"])
        try:
            self.engine = StepEngine(agent, self.link, robot_ids, peers, self.conf["step_timeout_s"])
        except AlgorithmError as exc:
            raise OnlineError(str(exc)) from None
        self.peers = self.engine.peers
        self._t0: float | None = None

    @property
    def stats(self) -> Counter[str]:
        """Counters of the link (degradations, ``late``, ``duplicate``, ``too_far_ahead``, ``wait_s``)."""
        return self.link.stats

    def start(self) -> list[str]:
        """Wait (``connect_timeout_s``) until every peer is connected; returns those that are not."""
        missing = self.net.wait_connected(self.conf["connect_timeout_s"])
        if missing:
            log.warning("robot %s: starting without %s (not connected after %.0f s); they may join later",
                        self.agent.robot_id, missing, self.conf["connect_timeout_s"])
        return missing

    def _pace(self, t: int) -> None:
        rate = float(self.conf["rate_hz"])
        if self._t0 is None:
            self._t0 = time.monotonic() - (t / rate if rate > 0 else 0.0)
        if rate > 0:
            delay = self._t0 + t / rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)

    def step(self, image: np.ndarray, context: FrameContext, stamp_s: float | None = None) -> StepResult:
        """One step of this robot; returns its pair records (ego = this robot) and its robot record."""
        self._pace(int(context.step))
        return drive([self.engine.step(image, context, stamp_s)])[0]

    def run(self, frames: Iterable[tuple[np.ndarray, FrameContext, float | None]]) -> Iterator[StepResult]:
        """:meth:`start`, then :meth:`step` for every ``(image, context, stamp_s)``."""
        self.start()
        for image, context, stamp in frames:
            yield self.step(image, context, stamp)
