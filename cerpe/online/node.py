"""One robot of a team, online: its :class:`~cerpe.algorithm.StepEngine` over a :class:`ZenohLink`.

The phases of a step are the engine's, the same as in :class:`~cerpe.algorithm.Team`.
This module adds what a robot process needs around them:

* waiting for the peers before step 0, and pacing the replay;
* a deadline per wait (``step_timeout_s``);
* publishing each step's relative-pose estimates for ROS 2
  (:class:`~cerpe.online.ros.EstimatePublisher`, on the link's Zenoh session);
* leaving: bye, then answering late image requests for at most ``linger_s``.

What the link counts is listed in :mod:`cerpe.online.zenoh_link`.
"""
from __future__ import annotations

import logging
import time
from collections import Counter
from typing import Any, Iterable, Iterator, Mapping, Sequence

import numpy as np

from ..algorithm import AlgorithmError, RobotAgent, StepEngine, drive
from ..config import merge_conf
from ..errors import CerpeError
from ..protocols import FrameContext
from ..records import StepResult
from . import ros
from .zenoh_link import ZenohLink

log = logging.getLogger(__name__)

ROS_KEYS = (*ros.KEY_FORMATS, "off")

default_conf: dict[str, Any] = {
    "step_timeout_s": 5.0,      # longest wait for the peers' frames of the same step (descriptors, replies, poses)
    "connect_timeout_s": 30.0,  # before step 0: wait this long for every peer to be up
    "rate_hz": 0.0,             # replay rate: step t starts no earlier than t / rate_hz after step 0; 0 = free
    "linger_s": 10.0,           # after the last step: answer requests until every peer said bye, at most this long
    "ros": {**ros.default_conf},  # estimates out: key_format rmw_zenoh | ros2dds | off, domain_id, distro
}


class OnlineError(CerpeError, ValueError):
    """Bad online configuration or arguments (robot id, encounter, option value)."""


class RobotNode:
    """Runs one robot's agent against its peers over a :class:`ZenohLink`.

    Args:
        agent: this robot's agent (its ``index`` is its wire sender id).
        link: this robot's open link (the node closes it in :meth:`close`).
        robot_ids: every robot of the encounter in wire-index order (index = position).
        peers: the robots it exchanges with and makes pair records for (default:
            every other robot of ``robot_ids``).
        conf: overrides of :data:`default_conf` (strict).

    Raises:
        OnlineError, ConfigError, RosError: a bad option, a team or robot name
            that cannot name a ROS topic while estimates go out.
    """

    def __init__(self, agent: RobotAgent, link: ZenohLink, robot_ids: Sequence[str],
                 peers: Iterable[str] | None = None, conf: Mapping[str, Any] | None = None) -> None:
        self.conf = merge_conf(default_conf, conf, "online node conf")
        for key in ("step_timeout_s", "connect_timeout_s", "rate_hz", "linger_s"):
            if not float(self.conf[key]) >= 0:
                raise OnlineError(f"online node conf: {key} must be >= 0, got {self.conf[key]!r}")
        rconf = self.conf["ros"]
        if rconf["key_format"] not in ROS_KEYS:
            raise OnlineError(f"--ros-keys {rconf['key_format']!r}: expected one of {list(ROS_KEYS)}")
        ros.check_distro(rconf["distro"])
        self.agent, self.link = agent, link
        try:
            self.engine = StepEngine(agent, link, robot_ids, peers, float(self.conf["step_timeout_s"]))
        except AlgorithmError as exc:
            raise OnlineError(str(exc)) from None
        self.estimates = (None if rconf["key_format"] == "off"
                          else ros.EstimatePublisher(link.session, link.team, agent.robot_id, rconf))
        self.peers = self.engine.peers
        self.step_s: list[float] = []   # wall time of each step (after pacing): compute + waits
        self.missing_at_start: list[str] = []
        self.met: set[str] = set()  # peers whose link was up at the start or after some step
        self.n_published = 0
        self._t0: float | None = None

    @property
    def stats(self) -> Counter[str]:
        """Counters of the link (degradations, wire bytes per kind, ``late``, ``wait_s``, ...)."""
        return self.link.stats

    def start(self) -> list[str]:
        """Announce this robot and wait (``connect_timeout_s``) for every peer; returns those not up."""
        self.missing_at_start = self.link.wait_peers(self.peers, float(self.conf["connect_timeout_s"]))
        self.met |= set(self.peers) - set(self.missing_at_start)
        if self.missing_at_start:
            log.warning("robot %s: starting without %s; they may join later", self.agent.robot_id,
                        self.missing_at_start)
        return self.missing_at_start

    def _pace(self, t: int) -> None:
        rate = float(self.conf["rate_hz"])
        if self._t0 is None:
            self._t0 = time.monotonic() - (t / rate if rate > 0 else 0.0)
        if rate > 0:
            delay = self._t0 + t / rate - time.monotonic()
            if delay > 0:
                self.link.poll(delay)  # idle, still answering image requests

    def step(self, image: np.ndarray, context: FrameContext, stamp_s: float | None = None) -> StepResult:
        """One step of this robot: its pair records (ego = this robot) and robot record; estimates published."""
        self._pace(int(context.step))
        t0 = time.perf_counter()
        res = drive([self.engine.step(image, context, stamp_s)])[0]
        self.step_s.append(time.perf_counter() - t0)
        self.met |= self.link.present & set(self.peers)
        if self.estimates is not None:
            self.n_published += sum(p.T_cj_ci is not None for p in res.pairs)
            self.estimates.publish_pairs(res.pairs)
        return res

    def run(self, frames: Iterable[tuple[np.ndarray, FrameContext, float | None]]) -> Iterator[StepResult]:
        """:meth:`start`, then :meth:`step` for every ``(image, context, stamp_s)`` (the link stays open)."""
        self.start()
        for image, context, stamp in frames:
            yield self.step(image, context, stamp)

    def report(self) -> dict[str, Any]:
        """What ``online.json`` keeps: link counters, step times, estimates published."""
        return {"link": dict(self.link.stats), "step_s": list(self.step_s), "n_steps": len(self.step_s),
                "peers": list(self.peers), "missing_at_start": list(self.missing_at_start),
                "peers_met": sorted(self.met),
                "estimates_published": self.n_published,
                "ros_keys": {p: self.estimates.key(p) for p in self.peers} if self.estimates else {}}

    def close(self, linger_s: float | None = None) -> None:
        """Say bye and close the link (answering late requests until every peer said bye, at most ``linger_s``)."""
        self.link.close(float(self.conf["linger_s"] if linger_s is None else linger_s))

    def __enter__(self) -> "RobotNode":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close(0.0 if exc[0] is not None else None)
