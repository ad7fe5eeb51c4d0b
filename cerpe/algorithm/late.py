"""A robot's registrations that run apart from its step (a :class:`~cerpe.algorithm.registrar.Registrar`)
and land when ready.

:class:`LateRegistrations` is a collaborator of :class:`~cerpe.algorithm.agent.RobotAgent` over its
:class:`~cerpe.algorithm.state.RobotState`:

* :meth:`~LateRegistrations.submit` (phase 4): the step's joint pass (own views, then the received
  images) goes to the registrar; the step's own pass holds the own views only. The step's state is kept
  until the job lands (its own views' poses, scale and odometry state are what the job's estimates are
  read with);
* :meth:`~LateRegistrations.collect` (phase 8, once per step): the jobs finished since are read exactly as
  a synchronous pass is (:func:`~cerpe.algorithm.direct.direct_estimates`), as of the step they were
  requested at (``StepState.landed``);
* :meth:`~LateRegistrations.bring_forward`: such an estimate ``T_cj_ci`` of step ``t0`` is carried to this
  step ``t`` with both odometries, ``X_j(t)^-1 X_j(t0) T X_i(t0)^-1 X_i(t)`` (what propagation does with an
  anchor); it then counts as this step's direct estimate (reason ``registration-late``). Where the
  peer's pose of ``t0`` or ``t`` is unknown the estimate is dropped (``registration:late-no-pose``).

Lateness (steps and seconds from submission to landing) is kept per robot
(``RobotState.registration_lateness``).
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..geometry import propagate_relative_pose
from ..protocols import BackboneOutput, View
from ..scale import recover_scale
from .config import AlgorithmConfig, AlgorithmError
from .direct import Estimate, direct_estimates
from .registrar import Registrar, RegistrationJob
from .state import RobotState, StepState


@dataclass
class Pending:
    """A submitted job: the step's state, the job's views, where each peer's image sits in them, and the
    robot's odometry pose at that step (set when the step ends)."""

    state: StepState
    views: list[View]
    collab_index: dict[str, int]
    X_i: np.ndarray | None = None


@dataclass
class Landed:
    """A peer's estimates from a job that landed this step, as of step ``step`` (``X_i``: this robot's pose
    then), or the reason it gave none."""

    step: int
    ests: list[Estimate]
    reason: str
    X_i: np.ndarray


def checked_output(out: object, n_views: int, where: str, degrade: Callable[[str], None]) -> BackboneOutput:
    """``out`` of a pass over ``n_views`` views with every non-finite placed pose made invalid (counted
    ``backbone:non-finite-pose``); :class:`AlgorithmError` when it is not a :class:`BackboneOutput` of
    ``n_views`` views."""
    if not isinstance(out, BackboneOutput) or len(out.valid) != n_views:
        n = len(out.valid) if isinstance(out, BackboneOutput) else type(out).__name__
        raise AlgorithmError(f"{where}: backbone returned {n} views for {n_views} given")
    valid = np.asarray(out.valid, dtype=bool).copy()
    for k in range(n_views):
        if valid[k] and not np.all(np.isfinite(out.T_frame_cam[k])):
            valid[k] = False
            out.reasons[k] = "non-finite pose"
            degrade("backbone:non-finite-pose")
    out.valid = valid
    return out


class LateRegistrations:
    """See the module docstring; ``registrar`` runs the jobs."""

    def __init__(self, state: RobotState, registrar: Registrar, config: AlgorithmConfig) -> None:
        self.s, self.registrar, self.config = state, registrar, config

    def submit(self, st: StepState, views: list[View], collab_index: dict[str, int]) -> None:
        """Queue the joint pass ``views`` of step ``st``; a job the full queue dropped is counted
        (``registration:dropped``) and its images give no estimate."""
        for job in self.registrar.submit(RegistrationJob(st.step, list(views))):
            if self.s.pending.pop(job.step, None) is not None:
                self.s.degrade("registration:dropped")
        self.s.pending[st.step] = Pending(st, list(views), dict(collab_index))
        st.pending_peers.update(collab_index)
        for other in collab_index:
            st.gate_reason[other] = "registration-pending"

    def step_done(self, st: StepState) -> None:
        """The step ends: its job (if still pending) will be read with this odometry pose."""
        pend = self.s.pending.get(st.step)
        if pend is not None:
            pend.X_i = self.s.X.copy()

    def collect(self, st: StepState) -> None:
        """Read every job that landed since the last step (once per step) into ``st.landed``."""
        if st.collected:
            return
        st.collected = True
        now = time.perf_counter()
        for res in self.registrar.landed():
            pend = self.s.pending.pop(res.step, None)
            if pend is None:  # dropped, or of an encounter before a reset
                continue
            self.s.registration_lateness.append((st.step - res.step, now - res.submitted_s))
            if res.out is None:
                self.s.degrade("registration:failed")
                continue
            st0 = pend.state
            try:
                out = checked_output(res.out, len(st0.own_views) + len(pend.collab_index),
                                     self.s.where(st0.step), self.s.degrade)
            except AlgorithmError:
                self.s.degrade("registration:failed")
                continue
            X_i = pend.X_i if pend.X_i is not None else self.s.X.copy()
            then = dataclasses.replace(st0, out=out, collab_index=pend.collab_index, directs={},
                                       scale=self.job_scale(pend, out))
            for other in pend.collab_index:
                ests, reason = direct_estimates(then, other, X_i, self.s.degrade)
                st.landed[other] = Landed(res.step, ests, reason, X_i)

    def job_scale(self, pend: Pending, out: BackboneOutput) -> float:
        """The metric scale of a job's pass, as :meth:`~cerpe.algorithm.agent.RobotAgent.estimate_scale`
        finds it for a step's pass (its keyframes' depth references, else the current view's); NaN when
        none (the job then gives no estimate: ``no-scale``). 1 for a pass in metres."""
        if out.metric_unit and self.config.scale.metric_unit:
            return 1.0
        st0 = pend.state
        idx = sorted(k for k in st0.own_views if k != 0 and k != st0.prev_index) or [0]
        est = recover_scale([pend.views[k].depth_m for k in idx],
                            [out.depth[k] if out.valid[k] else None for k in idx],
                            [out.depth_conf[k] for k in idx], min_pixels=self.config.scale.min_pixels)
        return float(est.scale) if est.ok else float("nan")

    def bring_forward(self, st: StepState, other: str, landed: Landed) -> tuple[list[Estimate], str]:
        """``landed``'s estimates carried to step ``st`` (see the module docstring)."""
        if not landed.ests or landed.step == st.step:
            return landed.ests, landed.reason
        plog = self.s.pose_logs.get(other)
        pose = self.s.poses.get(other)
        X_j0 = None if plog is None else plog.exact(landed.step)
        if pose is not None and pose[0] == st.step:
            X_j = pose[1]
        else:
            X_j = None if plog is None else plog.exact(st.step)
            if X_j is None and plog is not None:
                X_j = plog.bridged(st.step)
        if X_j0 is None or X_j is None:
            self.s.degrade("registration:late-no-pose")
            return [], "registration-late-no-pose"
        return [(via, step, propagate_relative_pose(T, landed.X_i, self.s.X, X_j0, X_j), n)
                for via, step, T, n in landed.ests], ""
