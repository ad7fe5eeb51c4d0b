"""A robot's direct estimates of a peer at one step: from its own joint pass, and shared by the peer.

:func:`direct_estimates` reads the pass (:class:`~cerpe.algorithm.state.StepState`): the
collaborator view's registrations against single own views, most inliers first, else its
joint-pass pose. With ``messages.share_estimates`` (our extension) each robot also
broadcasts the best of them per peer (:func:`estimate_message`); the peer takes the inverse
(:func:`shared_estimate`) as an estimate of its own, marked :data:`SHARED_VIA`. Estimates are
tuples ``(pass index of the own view, that view's step or -1 for the current frame, T_cj_ci
[4,4] metric, inliers or -1)``.
"""
from __future__ import annotations

from typing import Callable, Mapping

import numpy as np

from ..geometry import scale_translation, se3_inverse
from ..messages import EstimateMessage
from ..protocols import REASON_APPEARANCE
from .poses import direct_relative, registered_relative
from .state import StepState

Estimate = tuple[int, int, np.ndarray, int]
# pass index and step of a shared estimate: the peer's registration, through none of this robot's views
SHARED_VIA = -2
REASON_SHARED = "shared-estimate"  # the reason of a reported estimate that the peer shared


def via_to_current(st: StepState, via: int, X: np.ndarray) -> np.ndarray | None:
    """``T_via_ci``, metric: identity for the current view, through the pass when it placed both,
    else through the robot's odometry ``X`` (the view's stored pose); None without either."""
    out = st.out
    if via == 0:
        return np.eye(4)
    if out.valid[via] and out.valid[0]:
        return scale_translation(se3_inverse(out.T_frame_cam[via]) @ out.T_frame_cam[0], st.scale)
    if st.ego_status in ("ok", "external"):  # external: the robot's own odometry (online)
        return se3_inverse(st.own_views[via][1]) @ X
    return None


def direct_estimates(st: StepState, other: str, X: np.ndarray,
                     degrade: Callable[[str], None]) -> tuple[list[Estimate], str]:
    """This step's direct estimates of ``other`` (:func:`pass_estimates`); online by stamps, where the
    peer's view was captured at another instant, each is moved by the peer's motion since
    (``st.collab_motion``; None: unknown, so none, ``peer-motion-unknown``)."""
    ests, why = pass_estimates(st, other, X, degrade)
    if other not in st.collab_motion:
        return ests, why
    M = st.collab_motion[other]
    return ([], "peer-motion-unknown") if M is None else ([(k, v, M @ T, n) for k, v, T, n in ests], why)


def pass_estimates(st: StepState, other: str, X: np.ndarray,
                   degrade: Callable[[str], None]) -> tuple[list[Estimate], str]:
    """This step's direct estimates of ``other`` from the robot's own pass and ``reason`` when none.

    Through the collaborator's registrations against single own views, most inliers first,
    when the backbone gives them; else through the joint pass (``T_frame_cam``; pass index 0,
    step -1, inliers ``BackboneOutput.support``). Counts what it finds wrong through ``degrade``.
    """
    out, k = st.out, st.collab_index.get(other)
    if k is None:
        return [], st.gate_reason.get(other, "reply-missing")
    regs = [r for r in out.registrations.get(k, ()) if r.via in st.own_views]
    if not regs:
        if not out.valid[k] and k < len(out.reasons) and out.reasons[k] == REASON_APPEARANCE:
            degrade("direct:appearance-mismatch")  # placed by keypoints, contradicted by the images
            return [], "appearance-mismatch"
        if not out.valid[k]:
            return [], "collaborator-view-not-placed"
        if not out.valid[0]:
            return [], "own-view-not-placed"
        if not np.isfinite(st.scale):
            return [], "no-scale"
        T = direct_relative(out.T_frame_cam[0], out.T_frame_cam[k], st.scale)
        return [(0, -1, T, int(out.support[k]))], ""  # BackboneOutput checks one support per view
    if not np.isfinite(st.scale):
        return [], "no-scale"
    ests = []
    for r in sorted(regs, key=lambda r: -r.inliers):
        T_via_ci = via_to_current(st, r.via, X)
        if not np.all(np.isfinite(r.T_via_cam)):
            degrade("backbone:non-finite-pose")
        elif T_via_ci is not None:
            ests.append((r.via, -1 if r.via == 0 else st.own_views[r.via][0],
                         registered_relative(r.T_via_cam, T_via_ci, st.scale), int(r.inliers)))
    return ests, "" if ests else "registrations-not-usable"


def estimate_message(sender: int, step: int, best: Mapping[int, Estimate]) -> EstimateMessage:
    """The frame sharing the best own estimate per peer (wire index -> estimate), peers in index order."""
    return EstimateMessage(sender, step, tuple((int(j), e[2], int(e[3])) for j, e in sorted(best.items())))


def shared_estimate(msg: EstimateMessage, own_index: int) -> Estimate | None:
    """The peer's estimate of this robot in ``msg``, as this robot's: ``T_cj_ci`` inverted, marked
    :data:`SHARED_VIA`; None when it has none (or a degenerate one)."""
    got = msg.for_target(own_index)
    if got is None or not np.all(np.isfinite(got[0])):
        return None
    return (SHARED_VIA, SHARED_VIA, se3_inverse(got[0]), int(got[1]))
