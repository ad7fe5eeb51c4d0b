"""One robot of a team, online: its engine over a :class:`ZenohLink`, its estimates out.

By stamps (the link's ``sync: stamps``, what ``cerpe online`` runs), :class:`RobotNode` takes frames
from a source (:mod:`cerpe.online.sources`: a replay, or the robot's ROS 2 topics) at its own pace
and runs a :class:`~cerpe.algorithm.StampEngine`; in lock-step (``sync: lockstep``) it runs the team's
:class:`~cerpe.algorithm.StepEngine` step by step, which reproduces ``cerpe run``. Around the engine:

* waiting for the peers before the first frame (lock-step, and a replay by stamps: at most
  ``connect_timeout_s``), pacing a lock-step replay (``rate_hz``);
* the estimates of each frame out (:class:`~cerpe.online.publish.EstimatePublisher`): ROS 2 topics
  with their covariance (the pose graph's, or the switch's model), optionally TF, the newest on a
  queryable. By stamps the records carry the covariance published;
* leaving: bye, then answering late image requests for at most ``linger_s``.

What the link counts is listed in :mod:`cerpe.online.zenoh_link`.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from collections import Counter
from typing import Any, Iterable, Iterator, Mapping, Sequence

import numpy as np

from ..algorithm import AlgorithmError, RobotAgent, StepEngine, drive
from ..algorithm.stamp_engine import StampEngine
from ..algorithm.switch_cov import switch_cov
from ..config import merge_conf
from ..errors import CerpeError
from ..protocols import FrameContext
from ..records import StepResult
from . import ros
from .publish import EstimatePublisher
from .sources import Frame
from .zenoh_link import ZenohLink

log = logging.getLogger(__name__)

ROS_KEYS = (*ros.KEY_FORMATS, "off")

default_conf: dict[str, Any] = {
    "step_timeout_s": 5.0,      # lock-step: longest wait for the peers' frames of the same step
    "wait_s": 0.5,              # by stamps: longest wait for a peer's descriptor or pose near a frame's stamp
    "reply_timeout_s": 2.0,     # by stamps: longest wait for the replies to a frame's image requests
    "connect_timeout_s": 30.0,  # before the first frame: wait this long for every peer (lock-step, replays)
    "rate_hz": 0.0,             # lock-step replay rate: step t starts no earlier than t / rate_hz after step 0
    "linger_s": 10.0,           # after the last step: answer requests until every peer said bye, at most this long
    "tf": False,                # also publish the estimates as TF (peer cameras under this robot's camera)
    "ros": {**ros.default_conf},  # estimates out: key_format rmw_zenoh | ros2dds | off, domain_id, distro
}


class OnlineError(CerpeError, ValueError):
    """Bad online configuration or arguments (robot id, encounter, option value)."""


class RobotNode:
    """Runs one robot's agent against its peers over a :class:`ZenohLink` (its ``sync`` decides how).

    Args:
        agent: this robot's agent (its ``index`` is its wire sender id).
        link: this robot's open link (the node closes it in :meth:`close`).
        robot_ids: every robot of the team in wire-index order (index = position).
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
        for key in ("step_timeout_s", "wait_s", "reply_timeout_s", "connect_timeout_s", "rate_hz", "linger_s"):
            if not float(self.conf[key]) >= 0:
                raise OnlineError(f"online node conf: {key} must be >= 0, got {self.conf[key]!r}")
        rconf = self.conf["ros"]
        if rconf["key_format"] not in ROS_KEYS:
            raise OnlineError(f"--ros-keys {rconf['key_format']!r}: expected one of {list(ROS_KEYS)}")
        ros.check_distro(rconf["distro"])
        self.agent, self.link = agent, link
        self.sync = link.wire.mode
        try:
            self.engine: Any = (StepEngine(agent, link, robot_ids, peers, float(self.conf["step_timeout_s"]))
                                if self.sync == "lockstep" else
                                StampEngine(agent, link, robot_ids, peers, float(self.conf["wait_s"]),
                                            float(self.conf["reply_timeout_s"])))
        except AlgorithmError as exc:
            raise OnlineError(str(exc)) from None
        self.estimates = (None if rconf["key_format"] == "off" else
                          EstimatePublisher(link.session, link.team, agent.robot_id, rconf, tf=bool(self.conf["tf"])))
        self.peers = self.engine.peers
        self.step_s: list[float] = []   # wall time of each step (after pacing): compute + waits
        self.latency_s: list[float] = []  # by stamps: a frame's arrival to its estimates published (frames with one)
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

    # ------------------------------------------------------------------ lock-step
    def _pace(self, t: int) -> None:
        rate = float(self.conf["rate_hz"])
        if self._t0 is None:
            self._t0 = time.monotonic() - (t / rate if rate > 0 else 0.0)
        if rate > 0:
            delay = self._t0 + t / rate - time.monotonic()
            if delay > 0:
                self.link.poll(delay)  # idle, still answering image requests

    def step(self, image: np.ndarray, context: FrameContext, stamp_s: float | None = None) -> StepResult:
        """One lock-step step of this robot: its pair records (ego = this robot) and robot record; estimates out."""
        self._pace(int(context.step))
        t0 = time.perf_counter()
        res = drive([self.engine.step(image, context, stamp_s)])[0]
        self.step_s.append(time.perf_counter() - t0)
        self.met |= self.link.present & set(self.peers)
        self._publish(res, self._covariances(res))
        return res

    def run(self, frames: Iterable[tuple[np.ndarray, FrameContext, float | None]]) -> Iterator[StepResult]:
        """Lock-step: :meth:`start`, then :meth:`step` for every ``(image, context, stamp_s)`` (the link stays open)."""
        self.start()
        for image, context, stamp in frames:
            yield self.step(image, context, stamp)

    # ------------------------------------------------------------------ by stamps
    def step_frame(self, frame: Frame) -> StepResult:
        """One frame by stamps; its records carry the covariance of what was published."""
        t0 = time.perf_counter()
        T = frame.T_odom_cam
        degr = list(frame.degradations)
        if T is not None and not np.all(np.isfinite(T)):  # the robot's odometry has nothing at this frame
            T = self.agent.X
            degr.append("input:no-odometry")
        res = self.engine.step(frame.image, frame.context, frame.stamp_s, T, degr)
        covs = self._covariances(res)
        res = dataclasses.replace(res, pairs=[p if p.cov is not None or covs.get(p.other) is None
                                              else dataclasses.replace(p, cov=covs[p.other]) for p in res.pairs])
        self.step_s.append(time.perf_counter() - t0)
        self.met |= self.link.present & set(self.peers)
        self._publish(res, covs)
        if any(p.T_cj_ci is not None for p in res.pairs):  # published now (or would be, with --ros-keys off)
            self.latency_s.append(time.time() - frame.arrival_s)
        return res

    def run_stamps(self, source: Any, wait_for_team: bool = False) -> Iterator[StepResult]:
        """By stamps: announce, (a replay: wait for the peers, start at the team's time), then a step per frame."""
        clock = getattr(source, "clock", None)
        if clock is not None:
            self.link.clock = clock
        if wait_for_team:
            self.start()
            self.link.poll(0.3)  # peers running already: their clocks come with their frames
        else:
            self.link.announce()
        if hasattr(source, "start"):
            source.start(self.link.peer_clock_now())
            self.link.clock = source.clock
        for frame in source.frames():
            yield self.step_frame(frame)

    # ------------------------------------------------------------------ out
    def _covariances(self, res: StepResult) -> dict[str, np.ndarray | None]:
        """peer -> the covariance of this step's estimate (the record's, else the switch's model)."""
        return {p.other: p.cov if p.cov is not None else switch_cov(self.agent, p)
                for p in res.pairs if p.T_cj_ci is not None}

    def _publish(self, res: StepResult, covs: Mapping[str, np.ndarray | None]) -> int:
        if self.estimates is None:
            return 0
        n = self.estimates.publish_pairs(res.pairs, covs)
        self.n_published += n
        return n

    def report(self) -> dict[str, Any]:
        """What ``online.json`` keeps: link counters, step times, latency, estimates published, peer events."""
        lat = np.asarray(self.latency_s)
        out = {"sync": self.sync, "link": dict(self.link.stats), "step_s": list(self.step_s),
               "n_steps": len(self.step_s), "peers": list(self.peers), "missing_at_start": list(self.missing_at_start),
               "peers_met": sorted(self.met), "estimates_published": self.n_published,
               "ros_keys": {p: self.estimates.key(p) for p in self.peers} if self.estimates else {},
               "latency_s": list(self.latency_s),
               "latency_median_s": float(np.median(lat)) if lat.size else None,
               "latency_p90_s": float(np.percentile(lat, 90)) if lat.size else None}
        if self.sync == "stamps":
            out["peer_events"] = [list(e) for e in self.engine.events]
            out["peer_poses"] = dict(self.engine.pose_stats)
            out["replies_served"] = self.engine.ring.n_replies
            out["clock_offsets_s"] = {p: self.link.offsets.estimate(p) for p in self.peers}
        return out

    def close(self, linger_s: float | None = None) -> None:
        """Say bye and close the link (answering late requests until every peer said bye, at most ``linger_s``)."""
        if self.estimates is not None:
            self.estimates.close()
        self.link.close(float(self.conf["linger_s"] if linger_s is None else linger_s))

    def __enter__(self) -> "RobotNode":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close(0.0 if exc[0] is not None else None)
