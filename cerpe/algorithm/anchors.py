"""Anchor verification for one ordered pair of robots.

A direct estimate ``T_cj_ci`` becomes the pair's **anchor** (what propagation
starts from) only when something independent agrees with it:

* an existing anchor, propagated to the estimate's step with both odometries,
  within a tolerance that grows with the steps since that anchor and with the
  distance both robots travelled since (odometry drifts);
* with no anchor yet: a second estimate of the same step through another own
  view (two registrations that agree);
* or, with no anchor yet, the recent unverified candidates (:func:`consensus`).
  Their largest group (with the estimate) that agree pairwise in rotation AND
  translation, each carried to the newer one's step with both odometries, must
  have ``verify_support`` + 1 estimates or more. The estimates that agree with
  all of it in rotation must be at least ``verify_fraction`` of the recent ones.
  Its newest member becomes the anchor and the candidates outside it are
  rejected (a translation outlier with the right rotation cannot block
  estimates that agree).

An estimate that agrees with the anchor but stands on fewer than ``min_inliers``
registration inliers is *weak*: the pair keeps the anchor (and propagates it
instead of reporting the estimate). An estimate that disagrees with the anchor is
*rejected* (the pair keeps the anchor). When ``replace_after`` rejected estimates
of the last ``candidate_steps`` steps agree with the newest of them, the newest replaces it (persistent
disagreement: the anchor was the wrong one). Before any anchor is
verified, the newest unverified estimate may be propagated for at most
``max_unverified_steps`` steps, and only with ``report_unverified`` (without it,
nothing is reported before an estimate is verified).

Pure numpy + :mod:`cerpe.geometry`; no robot, link or record here. A pose-graph
back end can sit beside it (it would consume the same :class:`Anchor` stream).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from ..geometry import propagate_relative_pose, rotation_angle, se3_inverse
from ..knobs import Group, knob

Verdict = Literal["verified", "accepted", "unverified", "rejected", "replaced", "weak"]
# verdicts whose estimate is not reported (the anchor's propagation is): the agent's rule, which replays share
NOT_REPORTED: frozenset[str] = frozenset({"rejected", "weak"})
# verdicts whose estimate set the pair's anchor: verification's, and "unchecked" (verification off, the paper's
# switch); the request policy and the pose graph read them (the graph adds "", no verdict given)
SETS_ANCHOR: frozenset[str] = frozenset({"verified", "accepted", "replaced", "unchecked"})


# Tolerances that grow with what separates two estimates.
ROT_DRIFT_PER_STEP = 0.005  # rotation per step between them (rad)
TRANS_DRIFT_FRAC = 0.1  # translation per metre the two robots travelled between them (m/m; odometers summed)
TRANS_REL = 0.2  # translation per metre between the cameras (m/m; rotation or scale errors move a far camera more)
# Two registrations of one step through different own views verify each other within these (rad, m; the
# translation tolerance also grows by TRANS_REL per metre between the cameras).
AGREE_ROT_RAD = 0.15
AGREE_TRANS_M = 0.3


@dataclass(frozen=True)
class AnchorConfig(Group):
    """When a direct estimate becomes the pair's anchor (see the module docstring).

    Take two estimates ``k`` steps apart, between which the robots travelled ``d`` metres together.
    They agree when the rotation between them is at most ``rot_tol_rad + ROT_DRIFT_PER_STEP * k``
    and their translations differ by at most
    ``trans_tol_m + TRANS_DRIFT_FRAC * d + TRANS_REL * |t|``
    (``|t|`` the newer estimate's distance between the cameras).
    """

    verify: bool = knob(True, "a direct estimate becomes the anchor only when something independent agrees "
                        "(False: the paper's switch, every direct estimate is the new anchor)")
    rot_tol_rad: float = knob(0.15, "two estimates agree within this rotation right after the anchor (rad)", low=0)
    trans_tol_m: float = knob(0.3, "two estimates agree within this translation right after the anchor (m)", low=0)
    min_inliers: int = knob(40, "an estimate that agrees with the anchor on fewer registration inliers is weak: "
                            "the anchor is propagated instead (0: off)", low=0)
    replace_after: int = knob(5, "rejected estimates that agree with each other and replace the anchor", low=1)
    candidate_steps: int = knob(10, "steps an unverified or rejected estimate stays available to verify a later "
                                "one", low=0)
    verify_support: int = knob(2, "without an anchor, recent agreeing estimates (besides the newest) that "
                               "verify the newest", low=1)
    verify_fraction: float = knob(0.5, "and the recent estimates agreeing with that group in rotation must be at "
                                  "least this fraction of the others (0: any number)", low=0, high=1)
    report_unverified: bool = knob(True, "report a direct estimate nothing has verified yet (False: hold it "
                                   "until something agrees)")
    max_unverified_steps: int = knob(2, "before any anchor is verified, an unverified estimate is carried at "
                                     "most this many steps (the pose graph likewise)", low=0)
    max_odo_rot_step: float = knob(1.0, "the pair forgets its anchor when either odometry turns more than "
                                   "this in one step (rad; 0: never)", low=0)


@dataclass
class Anchor:
    """A direct estimate with what propagating it needs.

    Attributes:
        step: the step it was measured at.
        T_cj_ci: ``[4,4]`` metric pose of camera i in camera j at that step.
        X_i, X_j: ``[4,4]`` both robots' odometry poses ``T_odom_cam`` at that step.
        odo_i, odo_j: both robots' odometers (metres travelled since their first
            step, summed over the poses seen) at that step; 0 when unknown.
        metric: False when the translations are not in metres (no metric depth:
            the scale was set to 1); translations are then not compared.
        inliers: the registration's inlier count (-1: unknown).
    """

    step: int
    T_cj_ci: np.ndarray
    X_i: np.ndarray
    X_j: np.ndarray
    odo_i: float = 0.0
    odo_j: float = 0.0
    metric: bool = True
    inliers: int = -1

    def propagated(self, X_i: np.ndarray, X_j: np.ndarray) -> np.ndarray:
        """``T_cj_ci`` moved to odometry poses ``X_i``, ``X_j`` (paper Eq. propagation)."""
        return propagate_relative_pose(self.T_cj_ci, self.X_i, X_i, self.X_j, X_j)


def disagreement(old: Anchor, new: Anchor) -> tuple[float, float]:
    """``(rotation rad, translation m)`` between ``new`` and ``old`` propagated to ``new``'s poses."""
    T = old.propagated(new.X_i, new.X_j)
    D = se3_inverse(T) @ new.T_cj_ci
    return float(rotation_angle(D[:3, :3])), float(np.linalg.norm(new.T_cj_ci[:3, 3] - T[:3, 3]))


def tolerance(conf: AnchorConfig, old: Anchor, new: Anchor) -> tuple[float, float]:
    """``(rotation rad, translation m)`` two estimates may differ by (see :class:`AnchorConfig`)."""
    k = abs(new.step - old.step)
    rot = conf.rot_tol_rad + ROT_DRIFT_PER_STEP * k
    if not (old.metric and new.metric):
        return rot, float("inf")
    travelled = abs(new.odo_i - old.odo_i) + abs(new.odo_j - old.odo_j)
    return rot, (conf.trans_tol_m + TRANS_DRIFT_FRAC * travelled
                 + TRANS_REL * float(np.linalg.norm(new.T_cj_ci[:3, 3])))


def consistent(conf: AnchorConfig, old: Anchor, new: Anchor) -> tuple[bool, float, float]:
    """``(agree, rotation rad, translation m)`` of ``new`` against ``old`` propagated to it."""
    rot, trans = disagreement(old, new)
    rot_tol, trans_tol = tolerance(conf, old, new)
    return bool(rot <= rot_tol and trans <= trans_tol), rot, trans


def _cliques(adj: np.ndarray) -> list[frozenset[int]]:
    """The maximal cliques of the undirected graph ``adj`` (Bron-Kerbosch with pivoting)."""
    nb = [set(np.flatnonzero(row).tolist()) - {v} for v, row in enumerate(adj)]
    out: list[frozenset[int]] = []

    def grow(r: set[int], p: set[int], x: set[int]) -> None:
        if not p and not x:
            out.append(frozenset(r))
            return
        u = max(p | x, key=lambda v: len(p & nb[v]))
        for v in sorted(p - nb[u]):
            grow(r | {v}, p & nb[v], x & nb[v])
            p, x = p - {v}, x | {v}

    grow(set(), set(range(len(adj))), set())
    return out


def consensus(conf: AnchorConfig, pool: Sequence[Anchor]) -> list[int] | None:
    """Which of ``pool`` (estimates without an anchor, oldest first) verify each other: indices, or None.

    Every two are compared with the older carried to the newer's poses
    (:func:`consistent`: rotation, and translation within a tolerance that grows
    with the distance between the cameras and the metres travelled between the
    two). The group is the largest set that agree pairwise in both (of equal ones,
    the one with the newest member; None when another as large shares no member
    with it: two hypotheses). It verifies when it has ``verify_support`` + 1
    members or more, and the estimates that agree in rotation with all of it
    (members included) are at least ``verify_fraction`` of the others. So an
    estimate off in translation but with the right rotation neither joins the
    group nor blocks it; one off in rotation counts against it.
    """
    n = len(pool)
    full, rot = np.eye(n, dtype=bool), np.eye(n, dtype=bool)
    for b in range(n):
        for a in range(b):
            old, new = (pool[a], pool[b]) if pool[a].step <= pool[b].step else (pool[b], pool[a])
            r, t = disagreement(old, new)
            rot_tol, trans_tol = tolerance(conf, old, new)
            rot[a, b] = rot[b, a] = r <= rot_tol
            full[a, b] = full[b, a] = rot[a, b] and t <= trans_tol
    cliques = sorted(_cliques(full), key=lambda c: (len(c), max(c)), reverse=True)
    group = cliques[0]
    if len(group) < 2 or any(len(c) == len(group) and not c & group for c in cliques[1:]):
        return None
    if len(group) - 1 < conf.verify_support:
        return None
    support = sum(bool(rot[k, list(group)].all()) for k in range(n)) - 1  # members and rotation-only agreement
    return sorted(group) if support >= conf.verify_fraction * (n - 1) else None


@dataclass
class Check:
    """What :meth:`PairAnchors.offer` decided about one estimate.

    ``against``: step of what it was compared with (the anchor, a candidate, the
    same step for a second registration), -1 when nothing; ``rot_rad``,
    ``trans_m``: the disagreement with it (NaN when nothing was compared);
    ``dropped``: steps of the unverified candidates a verified group rejected
    (counted as rejected estimates).
    """

    verdict: Verdict
    against: int = -1
    rot_rad: float = float("nan")
    trans_m: float = float("nan")
    dropped: tuple[int, ...] = ()


@dataclass
class PairAnchors:
    """The verified anchor of one ordered pair, its unverified candidates and its challengers."""

    conf: AnchorConfig = field(default_factory=AnchorConfig)
    anchor: Anchor | None = None
    candidates: list[Anchor] = field(default_factory=list)
    challengers: list[Anchor] = field(default_factory=list)
    last_poses: tuple[int, np.ndarray, np.ndarray] | None = None

    def track(self, step: int, X_i: np.ndarray, X_j: np.ndarray) -> float:
        """Feed both robots' odometry poses ``T_odom_cam`` of ``step``; returns 0, or the rotation
        per step (rad) of the odometry jump that made the pair forget its anchor and candidates.

        Propagation moves an anchor by both odometries; when one turns by more than
        ``max_odo_rot_step`` per step since the last poses fed, that odometry failed
        (a lost track), and everything the pair kept would be carried through the
        failure. Off when ``max_odo_rot_step`` is 0.
        """
        last, self.last_poses = self.last_poses, (step, X_i.copy(), X_j.copy())
        if self.conf.max_odo_rot_step <= 0 or last is None or step <= last[0]:
            return 0.0
        turn = max(float(rotation_angle(se3_inverse(A)[:3, :3] @ B[:3, :3])) for A, B in ((last[1], X_i),
                                                                                        (last[2], X_j)))
        per_step = turn / (step - last[0])
        if per_step <= self.conf.max_odo_rot_step or (self.anchor is None and not self.candidates):
            return 0.0
        self._set(None)
        return per_step

    def offer(self, est: Anchor, others: Sequence[Anchor] = ()) -> Check:
        """Judge a direct estimate; ``others``: estimates of the same step through other own views.

        With an anchor: accepted when consistent with it (weak when it also stands on
        fewer than ``min_inliers`` known inliers: the anchor stays), else rejected (or, the
        ``replace_after``-th agreeing rejection, it replaces the anchor). Without:
        verified when one of ``others`` agrees with it or it is the newest of the
        group the recent candidates verify (:func:`consensus`). Rejected when that
        group leaves it out (its newest member becomes the anchor); else kept as a
        candidate (unverified).
        """
        if self.anchor is not None:
            return self._against_anchor(est)
        for other in others:
            rot, trans = disagreement(other, est)
            trans_tol = AGREE_TRANS_M + TRANS_REL * float(np.linalg.norm(est.T_cj_ci[:3, 3]))
            if rot <= AGREE_ROT_RAD and (trans <= trans_tol or not (est.metric and other.metric)):
                self._set(est)
                return Check("verified", est.step, rot, trans)
        self.candidates = [c for c in self.candidates if est.step - c.step <= self.conf.candidate_steps]
        pool = [*self.candidates, est]
        group = consensus(self.conf, pool)
        if group is not None:
            new = pool[group[-1]]
            dropped = tuple(c.step for k, c in enumerate(self.candidates) if k not in group)
            self._set(new)
            if new is est:  # compared with the newest other member of its group
                _, rot, trans = consistent(self.conf, pool[group[-2]], est)
                return Check("verified", pool[group[-2]].step, rot, trans, dropped)
            _, rot, trans = consistent(self.conf, new, est)  # the estimate is outside the group
            return Check("rejected", new.step, rot, trans, dropped)
        checks = [(c, *consistent(self.conf, c, est)) for c in reversed(self.candidates)]  # newest first
        support = [x for x in checks if x[1]]
        self.candidates.append(est)
        if not checks:
            return Check("unverified")
        c, _, rot, trans = (support or checks)[0]
        return Check("unverified", c.step, rot, trans)

    def _against_anchor(self, est: Anchor) -> Check:
        ok, rot, trans = consistent(self.conf, self.anchor, est)
        if ok and 0 <= est.inliers < self.conf.min_inliers:
            return Check("weak", self.anchor.step, rot, trans)
        if ok:
            self._set(est)
            return Check("accepted", self.anchor.step, rot, trans)
        against = self.anchor.step
        self.challengers = [c for c in self.challengers if est.step - c.step <= self.conf.candidate_steps] + [est]
        if 1 + sum(consistent(self.conf, c, est)[0] for c in self.challengers[:-1]) >= self.conf.replace_after:
            self._set(est)
            return Check("replaced", against, rot, trans)
        return Check("rejected", against, rot, trans)

    def _set(self, est: Anchor | None) -> None:
        self.anchor = est
        self.candidates.clear()
        self.challengers.clear()

    def carried(self, step: int) -> tuple[Anchor | None, bool]:
        """What a step without an accepted direct estimate propagates: ``(anchor, verified)``.

        The verified anchor when there is one; else, with ``report_unverified``, the
        newest unverified candidate while it is at most ``max_unverified_steps`` old;
        else None.
        """
        if self.anchor is not None:
            return self.anchor, True
        if self.conf.report_unverified and self.candidates and step - self.candidates[-1].step <= self.conf.max_unverified_steps:
            return self.candidates[-1], False
        return None, False
