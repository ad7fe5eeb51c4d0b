"""When to ask a collaborator for its image: the request policy.

The paper requests an image whenever the gate opens (``mode="gate"``, the default).
``mode="pays"`` (ours) asks only when the gate opens AND the image pays for its bytes:

* the pair has no verified anchor yet (an unverified candidate waits for the
  estimates that verify it), or its anchor is disputed (rejected estimates are
  waiting to replace it: they need more estimates to agree);
* the estimate's predicted uncertainty exceeds a threshold: the pose graph's
  marginal sigma of the previous step where ``backend.kind="graph"``, else a
  propagation model (:func:`propagation_sigma`: grows with the steps since the
  anchor and the metres both robots travelled since);
* more than ``max_steps`` steps passed since the last anchor (a fresh look now and
  then, whatever the model says);
* ``recheck_rot_rad``: the image that set the anchor disagreed in rotation by more than
  this with what it was checked against (the previous anchor propagated, or the candidate
  that verified it). One of the two is wrong, so the pair asks again at the next open gate.
  It does so until two estimates in a row agree within it, at most ``recheck_limit`` times
  in a row;

unless the pair is backing off. After ``miss_limit`` requests in a row whose image placed
nothing (the gate opened on views that do not overlap enough), it asks only every
``miss_backoff_steps`` steps (``unanchored_backoff_steps`` for a pair without an anchor), until
an image places again. With ``backoff_pending_exempt`` a pair whose estimates wait to be
verified (``pending``) does not back off.

How hard to try on an image that came through an open gate (:func:`try_hard`, whatever the mode):
a pair without an anchor asks the backbone for its costliest registration (``View.try_hard``: the
offline backbone's learned matcher on RGB-D passes). It does so at every request while at most
:data:`HARD_TRIES` requests placed nothing since the pair's last anchor-setting estimate
(``hard_misses``). After that it tries at the requests after ``HARD_TRIES - 1`` plus 2, 4, 8 ...
of those misses, at most :data:`HARD_BACKOFF_MAX_STEPS` apart. So first contact and wide
viewpoints get it, while a pair whose images never place (a repetitive room) pays for it ever
more rarely. A placement that sets no anchor (rejected or unverified) neither counts nor
restarts the schedule.

With ``messages.share_estimates`` (our extension) one more rule applies, in every mode but
``always``. A robot skips the request (``peer-shares``) when its last :data:`SHARED_SKIP_MISSES`
requests to a peer were misses, while that peer's estimates of the pair keep arriving (one at
the previous step). A miss is an image that placed nothing, or gave only a weaker estimate than
the peer's shared one (which was offered instead). It then asks again only every
:data:`SHARED_RETRY_STEPS` steps. Registration is not symmetric (a robot places a peer's image
through its own keyframes). So the image it cannot place costs the peer a reply for nothing,
while the peer's own registration gives the pair its estimate.

``mode="always"`` asks every peer at every step, gate or not (the "always send
images" reference of the Pareto figure). Pure: reads a :class:`PairView`, returns a
decision; the agent fills the view from its anchors, odometers and graph.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from ..knobs import Group, KnobError, knob
from .anchors import SETS_ANCHOR

MODES: tuple[str, ...] = ("gate", "pays", "always")

# The propagation model of the switch back end: a fresh anchor's predicted rotation sigma (rad) and its growth
# per step since; its position sigma (m) and growth per metre both robots travelled since (odometers summed).
ROT_SIGMA0_RAD = 0.01
ROT_SIGMA_PER_STEP = 0.0035
POS_SIGMA0_M = 0.05
POS_SIGMA_PER_M = 0.05
# try_hard: requests that may place nothing before the costliest registration backs off, and the largest gap
# (in such requests) between two tries after that
HARD_TRIES = 1
HARD_BACKOFF_MAX_STEPS = 32
# skip_for_shared (share_estimates only): misses in a row before a request is skipped while the peer shares its
# estimates of the pair, and the steps between two requests while skipping
SHARED_SKIP_MISSES = 2
SHARED_RETRY_STEPS = 8

# kept as the error of this module (a bad configuration is a KnobError naming the dotted key)
PolicyError = KnobError


@dataclass(frozen=True)
class PolicyConfig(Group):
    """When a gate that opened asks for the image (see the module docstring)."""

    mode: str = knob("gate", "gate: request whenever the gate opens (the paper); pays: only when the image pays "
                     "for its bytes (ours); always: every peer at every step", choices=MODES)
    max_sigma_rot_rad: float = knob(0.05, "pays: request when the predicted rotation sigma exceeds this (rad)", low=0)
    max_sigma_pos_m: float = knob(0.3, "pays: request when the predicted position sigma exceeds this (m)", low=0)
    max_steps: int = knob(30, "pays: request when more steps than this passed since the last anchor", low=0)
    miss_limit: int = knob(0, "pays: back off after this many requests in a row placed nothing (0: never)", low=0)
    miss_backoff_steps: int = knob(0, "pays: while backing off, ask every this many steps (0: never back off)", low=0)
    unanchored_backoff_steps: int = knob(0, "pays: the wait of a pair without an anchor while backing off "
                                         "(steps; 0: miss_backoff_steps)", low=0)
    backoff_pending_exempt: bool = knob(False, "pays: a pair whose estimates wait to be verified never backs off")
    recheck_rot_rad: float = knob(0.0, "pays: ask again while the estimate that set the anchor disagreed by more "
                                  "than this with what verified it (rad; 0: off)", low=0)
    recheck_limit: int = knob(0, "pays: at most this many such rechecks in a row (0 with a threshold: 1)", low=0)
    max_requests: int = knob(2, "images requested per step at most, the peers with the highest gate scores "
                                "first (0: no limit), count", low=0)


@dataclass(frozen=True)
class PairView:
    """What the policy knows about one ordered pair at the gate (before this step's pass).

    Attributes:
        anchored: the pair has a verified anchor (switch) or graph node.
        pending: unverified candidates or challengers wait for estimates to verify them.
        steps_since: steps since that anchor (or node) was measured.
        travelled_m: metres the two robots travelled since, odometers summed.
        sigma_rot_rad, sigma_pos_m: the graph's marginal sigma of the last step (NaN:
            none, e.g. the switch back end: the propagation model is used instead).
        misses: requests in a row (the newest last) whose image placed nothing.
        hard_misses: requests whose image placed nothing since the pair's last anchor-setting
            estimate (placements that set no anchor do not count; :func:`try_hard`).
        steps_since_ask: steps since the last request to this peer (large: never asked).
        anchor_rot_rad: rotation (rad) by which the estimate that set the anchor disagreed
            with what it was checked against (NaN: unknown).
        rechecks: placed estimates in a row that set the anchor disagreeing by more than
            ``recheck_rot_rad`` (the rule asks while this is at most ``recheck_limit``).
        steps_since_shared: steps since the peer last shared a usable estimate of the pair
            (``share_estimates``; large: never).
    """

    anchored: bool
    pending: bool = False
    steps_since: int = 0
    travelled_m: float = 0.0
    sigma_rot_rad: float = float("nan")
    sigma_pos_m: float = float("nan")
    misses: int = 0
    hard_misses: int = 0
    steps_since_ask: int = 1 << 30
    anchor_rot_rad: float = float("nan")
    rechecks: int = 0
    steps_since_shared: int = 1 << 30


@dataclass(frozen=True)
class AskLog:
    """What one robot remembers about its requests to one peer (the agent keeps one per peer).

    Attributes:
        step: the step of the last request.
        misses: requests in a row whose image placed nothing.
        hard_misses: requests whose image placed nothing since the last anchor-setting estimate.
        anchor_rot_rad: the disagreement of the last placed estimate that set the anchor
            (see :class:`PairView`).
        rechecks: anchor-setting estimates in a row that disagreed by more than ``recheck_rot_rad``.
    """

    step: int = -(1 << 30)
    misses: int = 0
    anchor_rot_rad: float = float("nan")
    rechecks: int = 0
    hard_misses: int = 0

    def view(self, step: int) -> dict:
        """The :class:`PairView` fields it fills at ``step``."""
        return {"misses": self.misses, "hard_misses": self.hard_misses, "steps_since_ask": step - self.step,
                "anchor_rot_rad": self.anchor_rot_rad, "rechecks": self.rechecks}


def after_request(conf: PolicyConfig, log: AskLog | None, step: int, placed: bool, verdict: str = "",
                  rot_rad: float = float("nan")) -> AskLog:
    """The log after a request at ``step``: did its image place, and did its estimate set the
    anchor (``verdict``), disagreeing by ``rot_rad`` with what it was checked against."""
    log = log or AskLog()
    if not placed:
        return AskLog(step, log.misses + 1, log.anchor_rot_rad, log.rechecks, log.hard_misses + 1)
    if verdict not in SETS_ANCHOR:  # rejected, unverified or weak: the anchor (if any) stays
        return AskLog(step, 0, log.anchor_rot_rad, log.rechecks, log.hard_misses)
    off = bool(conf.recheck_rot_rad) and math.isfinite(rot_rad) and rot_rad > conf.recheck_rot_rad
    return AskLog(step, 0, float(rot_rad), log.rechecks + 1 if off else 0, 0)


def propagation_sigma(view: PairView) -> tuple[float, float]:
    """``(rotation rad, position m)`` predicted sigma of the anchor propagated ``steps_since`` steps."""
    return (ROT_SIGMA0_RAD + ROT_SIGMA_PER_STEP * max(view.steps_since, 0),
            POS_SIGMA0_M + POS_SIGMA_PER_M * max(view.travelled_m, 0.0))


def backoff_steps(conf: PolicyConfig, misses: int, anchored: bool = True) -> int:
    """Steps between requests after ``misses`` requests in a row placed nothing (0: not backing off);
    ``anchored`` False: a pair without an anchor (``unanchored_backoff_steps`` when set)."""
    base = conf.miss_backoff_steps
    if not anchored and conf.unanchored_backoff_steps and base:
        base = conf.unanchored_backoff_steps
    if not (conf.miss_limit and base) or misses < conf.miss_limit:
        return 0
    return int(base)


def try_hard(view: PairView) -> bool:
    """Whether a pair asks the backbone for its costliest registration of this step's image (see the
    module docstring): never with an anchor. Without one, when ``n = view.hard_misses - HARD_TRIES + 1`` (requests that
    placed nothing since the last anchor-setting estimate) is at most 0, a power of two up to
    ``HARD_BACKOFF_MAX_STEPS``, or a multiple of it beyond."""
    if view.anchored:
        return False
    n = view.hard_misses - HARD_TRIES + 1  # 1 at the first miss past the tries
    if n <= 0:
        return True
    cap = HARD_BACKOFF_MAX_STEPS
    return n % cap == 0 if n > cap else n & (n - 1) == 0


def _backing_off(conf: PolicyConfig, view: PairView) -> bool:
    if conf.backoff_pending_exempt and view.pending:
        return False
    return view.steps_since_ask < backoff_steps(conf, view.misses, view.anchored)


def skip_for_shared(view: PairView) -> bool:
    """Whether a robot that shares estimates skips this request (see the module docstring).

    It skips when its last :data:`SHARED_SKIP_MISSES` requests placed nothing, the peer shared an
    estimate of the pair at the previous step, and fewer than :data:`SHARED_RETRY_STEPS` steps
    passed since it last asked."""
    return bool(view.misses >= SHARED_SKIP_MISSES and view.steps_since_shared <= 1
                and view.steps_since_ask < SHARED_RETRY_STEPS)


def decide(conf: PolicyConfig, gate_open: bool, view: PairView | None) -> tuple[bool, str]:
    """``(request, why)``; ``why`` names the rule that asked, or why a request was skipped.

    ``view`` is only read with ``mode="pays"`` (None there counts as "no anchor").
    """
    if conf.mode == "always":
        return True, "always"
    if not gate_open:
        return False, "gate-closed"
    if conf.mode == "gate":
        return True, "gate"
    if view is not None and _backing_off(conf, view):
        return False, "backoff"
    if view is None or not view.anchored:
        return True, "no-anchor"
    if view.pending:
        return True, "pending"
    if view.steps_since > conf.max_steps:
        return True, "stale"
    if (conf.recheck_rot_rad and math.isfinite(view.anchor_rot_rad) and view.anchor_rot_rad > conf.recheck_rot_rad
            and view.rechecks <= max(conf.recheck_limit, 1)):
        return True, "recheck"
    rot, pos = view.sigma_rot_rad, view.sigma_pos_m
    if not (math.isfinite(rot) and math.isfinite(pos)):
        rot, pos = propagation_sigma(view)
    if rot > conf.max_sigma_rot_rad or pos > conf.max_sigma_pos_m:
        return True, "uncertain"
    return False, "anchor-fresh"
