"""Seeded encounter worlds, ``cad-intersection`` (vehicles at urban junctions,
:mod:`cerpe.synth.cad_intersection`) and ``indoor-team`` (three ground robots in a furnished
room, :mod:`cerpe.synth.indoor_team`): the one entry point that draws an encounter's plan
(:class:`cerpe.synth.plan.EncounterPlan`).

Each scenario is drawn from a seed; :func:`plan_encounter` re-draws (up to
``max_attempts``) until a quick low-resolution (128 px wide) depth render shows the overlap of
some robot pair rising above 0.3 *and* falling below 0.05 (see
:func:`cerpe.synth.groundtruth.has_transition`).
"""
from __future__ import annotations

import logging

import numpy as np

from . import cad_intersection, indoor_team
from .errors import SynthError
from .groundtruth import has_transition, overlap_matrix
from .plan import EncounterPlan
from .renderer import render

log = logging.getLogger(__name__)

WORLDS = ("cad-intersection", "indoor-team")
MAX_ROBOTS = 8  # robots of one encounter at most (a team of eight: `cerpe bench --robots 2 3 5 8`)


def check_conf(world: str, conf: dict) -> None:
    """Raise :class:`SynthError` for unknown worlds or impossible sizes / counts."""
    if world not in WORLDS:
        raise SynthError(f"unknown world {world!r}; known worlds: {', '.join(WORLDS)}")
    W, H = conf.get("size", (0, 0))
    if not (16 <= int(W) <= 4096 and 16 <= int(H) <= 4096):
        raise SynthError(f"size {W}x{H}: width and height must be between 16 and 4096 pixels")
    if not 2 <= int(conf.get("n_frames", 0)) <= 2000:
        raise SynthError(f"n_frames {conf.get('n_frames')}: must be between 2 and 2000")
    if not 2 <= int(conf.get("n_robots", 0)) <= MAX_ROBOTS:
        raise SynthError(f"n_robots {conf.get('n_robots')}: must be between 2 and {MAX_ROBOTS}")
    if not 0.5 <= float(conf.get("fps", 0)) <= 60:
        raise SynthError(f"fps {conf.get('fps')}: must be between 0.5 and 60")


def plan_encounter(world: str, seed: int, index: int, conf: dict, max_attempts: int = 16) -> EncounterPlan:
    """Draw encounter ``index`` of ``world`` (deterministic in ``seed``, ``index``, ``conf``).

    Re-draws until the quick overlap check at low resolution shows a transition
    (some pair above 0.35 and below 0.03); after ``max_attempts`` the draw with
    the widest overlap range is kept and ``meta["transition_precheck"]`` is False.
    """
    check_conf(world, conf)
    planner = cad_intersection.draw_encounter if world == "cad-intersection" else indoor_team.draw_encounter
    best, best_spread = None, -1.0
    for attempt in range(max_attempts):
        plan = planner(seed, index, conf, attempt)
        if plan.meta.get("collision", False):
            continue  # vehicles would overlap: draw again without rendering anything
        ov = quick_overlap(plan)
        # margins: the final overlap is computed at full resolution and differs a little
        ok = has_transition(ov, high=0.35, low=0.03)
        n = ov.shape[1]
        spread = max(min(ov[:, i, j].max() - 0.3, 0.05 - ov[:, i, j].min()) for i in range(n) for j in range(n) if i != j)
        plan.meta["transition_precheck"] = bool(ok)
        if ok:
            return plan
        if spread > best_spread:
            best, best_spread = plan, spread
    if best is None:
        raise SynthError(f"{world} encounter {index} (seed {seed}): every one of {max_attempts} draws had "
                         f"colliding vehicles; try another seed or fewer frames")
    log.warning("%s encounter %d (seed %d): no overlap transition after %d draws; keeping the best one",
                world, index, seed, max_attempts)
    return best


def quick_overlap(plan: EncounterPlan, width: int = 128) -> np.ndarray:
    """``[T,N,N]`` overlap from depth-only renders at ``width`` pixels (for planning only)."""
    K = plan.intrinsics
    Ks = K.scaled(width / K.width)
    n, T = plan.T_world_cam.shape[:2]
    out = np.zeros((T, n, n))
    for t in range(T):
        depths = [render(plan.faces_at(t, viewer=k), plan.T_world_cam[k, t], Ks, plan.ctx, with_rgb=False).depth_m
                  for k in range(n)]
        out[t] = overlap_matrix(depths, [Ks] * n, list(plan.T_world_cam[:, t]), stride=1)
    return out
