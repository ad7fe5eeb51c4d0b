"""When to ask a collaborator for its image (issue 21, item 3): the request policy.

The paper requests an image whenever the gate opens (``mode="gate"``, the default).
``mode="pays"`` (ours) asks only when the gate opens AND the image pays for its bytes:

* the pair has no verified anchor yet (an unverified candidate waits for the
  estimates that verify it), or its anchor is disputed (rejected estimates are
  waiting to replace it: they need more estimates to agree);
* the estimate's predicted uncertainty exceeds a threshold: the pose graph's
  marginal sigma of the previous step where ``backend="graph"``, else a
  propagation model (:func:`propagation_sigma`: grows with the steps since the
  anchor and the metres both robots travelled since);
* more than ``max_steps`` steps passed since the last anchor (a fresh look now and
  then, whatever the model says);

unless the pair is backing off: after ``miss_limit`` requests in a row whose image placed
nothing (the gate opened on views that do not overlap enough), it asks only every
``miss_backoff_steps`` steps, the wait growing ``miss_backoff_growth`` times per further
miss up to ``miss_backoff_max_steps``, until an image places again (0: never backs off).
An open gate without overlap otherwise asks at every step, and those bytes buy nothing.
With ``backoff_anchored_only`` only a pair that has an anchor backs off: it keeps an
estimate (its anchor propagated) while it waits, whereas a pair without one loses every
frame it does not ask for (and an unverified candidate expires unless the next images
verify it).

``mode="always"`` asks every peer at every step, gate or not (the "always send
images" reference of the Pareto figure). Pure: reads a :class:`PairView`, returns a
decision; the agent fills the view from its anchors, odometers and graph.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

from ..errors import CerpeError

MODES: tuple[str, ...] = ("gate", "pays", "always")


class PolicyError(CerpeError, ValueError):
    """A request-policy configuration that cannot be used (names the field)."""


@dataclass(frozen=True)
class PolicyConfig:
    """Request policy (see the module docstring); ``CerpeConfig.request_policy``, a dict is accepted.

    Attributes:
        mode: ``gate`` (the paper: request whenever the gate opens), ``pays`` (ours),
            ``always`` (every peer, every step).
        max_sigma_rot_rad, max_sigma_pos_m: request when the predicted sigma of the
            estimate (rotation, position) exceeds these.
        max_steps: request when more steps than this passed since the last anchor.
        rot_sigma0_rad, rot_sigma_per_step: propagation model (switch back end): a
            fresh anchor's rotation sigma and its growth per step since.
        pos_sigma0_m, pos_sigma_per_m: the same for position, growing per metre the
            two robots travelled since the anchor (both odometers summed).
        miss_limit, miss_backoff_steps: back off after this many requests in a row placed
            nothing, asking every ``miss_backoff_steps`` steps (either 0: never back off).
        miss_backoff_growth, miss_backoff_max_steps: the wait grows this many times per
            miss beyond ``miss_limit``, up to this many steps (1, 0: a constant wait).
        backoff_anchored_only: only a pair with an anchor backs off.
    """

    mode: str = "gate"
    # thresholds checked on development data only (scripts/dev_policy.py; figures in the commit that says so)
    max_sigma_rot_rad: float = 0.05
    max_sigma_pos_m: float = 0.3
    max_steps: int = 30
    rot_sigma0_rad: float = 0.01
    rot_sigma_per_step: float = 0.0035
    pos_sigma0_m: float = 0.05
    pos_sigma_per_m: float = 0.05
    miss_limit: int = 0
    miss_backoff_steps: int = 0
    miss_backoff_growth: float = 1.0
    miss_backoff_max_steps: int = 0
    backoff_anchored_only: bool = False

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise PolicyError(f"request_policy: mode must be one of {list(MODES)}, got {self.mode!r}")
        for name in ("max_sigma_rot_rad", "max_sigma_pos_m", "rot_sigma0_rad", "rot_sigma_per_step",
                     "pos_sigma0_m", "pos_sigma_per_m"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise PolicyError(f"request_policy: {name} must be finite and >= 0, got {v!r}")
        if not (isinstance(self.miss_backoff_growth, (int, float)) and math.isfinite(self.miss_backoff_growth)
                and self.miss_backoff_growth >= 1):
            raise PolicyError(f"request_policy: miss_backoff_growth must be finite and >= 1, "
                              f"got {self.miss_backoff_growth!r}")
        if not isinstance(self.backoff_anchored_only, bool):
            raise PolicyError(f"request_policy: backoff_anchored_only must be true or false, "
                              f"got {self.backoff_anchored_only!r}")
        for name in ("max_steps", "miss_limit", "miss_backoff_steps", "miss_backoff_max_steps"):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 0):
                raise PolicyError(f"request_policy: {name} must be an integer >= 0, got {v!r}")


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
        steps_since_ask: steps since the last request to this peer (large: never asked).
    """

    anchored: bool
    pending: bool = False
    steps_since: int = 0
    travelled_m: float = 0.0
    sigma_rot_rad: float = float("nan")
    sigma_pos_m: float = float("nan")
    misses: int = 0
    steps_since_ask: int = 1 << 30


def propagation_sigma(conf: PolicyConfig, view: PairView) -> tuple[float, float]:
    """``(rotation rad, position m)`` predicted sigma of the anchor propagated ``steps_since`` steps."""
    return (conf.rot_sigma0_rad + conf.rot_sigma_per_step * max(view.steps_since, 0),
            conf.pos_sigma0_m + conf.pos_sigma_per_m * max(view.travelled_m, 0.0))


def backoff_steps(conf: PolicyConfig, misses: int) -> int:
    """Steps between requests after ``misses`` requests in a row placed nothing (0: not backing off)."""
    if not (conf.miss_limit and conf.miss_backoff_steps) or misses < conf.miss_limit:
        return 0
    wait = conf.miss_backoff_steps * conf.miss_backoff_growth ** (misses - conf.miss_limit)
    cap = conf.miss_backoff_max_steps or conf.miss_backoff_steps
    return int(min(max(wait, conf.miss_backoff_steps), max(cap, conf.miss_backoff_steps)))


def _backing_off(conf: PolicyConfig, view: PairView) -> bool:
    if conf.backoff_anchored_only and not view.anchored:
        return False
    return view.steps_since_ask < backoff_steps(conf, view.misses)


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
    rot, pos = view.sigma_rot_rad, view.sigma_pos_m
    if not (math.isfinite(rot) and math.isfinite(pos)):
        rot, pos = propagation_sigma(conf, view)
    if rot > conf.max_sigma_rot_rad or pos > conf.max_sigma_pos_m:
        return True, "uncertain"
    return False, "anchor-fresh"
