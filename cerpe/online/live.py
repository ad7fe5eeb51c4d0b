"""The encounter a robot online by stamps writes its run folder for: open-ended, ground truth by stamp.

By stamps a robot's records are the frames it took, until its input ended: a run folder's
encounter has no fixed number of steps (``n_steps`` None, :func:`cerpe.runfolder.write.run_encounter_to_folder`).
:class:`ReplayEncounter` is a manifest's encounter replayed (records keyed by the dataset's step,
its ground truth and overlap as they are); :class:`LiveEncounter` is a robot's topics, optionally with
a manifest's encounter for ground truth, looked up at each record's stamp (the ego frame's capture
time: both robots' poses there, interpolated between ground-truth samples at most ``max_gap_s``
apart, else the nearest within ``tol_s``).
"""
from __future__ import annotations

from types import SimpleNamespace
from typing import Any, Sequence

import numpy as np

from ..datasets.sync import poses_at
from ..geometry import paper_T_ij, viewing_angle

GT_TOLERANCE_S = 0.02  # nearest ground-truth pose within this of a stamp (s)
GT_MAX_GAP_S = 0.2     # interpolate between ground-truth poses at most this far apart (s)


class ReplayEncounter:
    """``enc`` with ``n_steps`` None: a replay by stamps writes the frames it took."""

    n_steps = None

    def __init__(self, enc: Any) -> None:
        self.enc = enc
        self.name, self.robots, self.overlap = enc.name, enc.robots, enc.overlap

    def gt_T_cj_ci(self, t: int, i: int, j: int) -> np.ndarray | None:
        return self.enc.gt_T_cj_ci(t, i, j)

    def gt_viewing_angle(self, t: int, i: int, j: int) -> float:
        return self.enc.gt_viewing_angle(t, i, j)


class LiveEncounter:
    """A robot's live frames: roster ``robot_ids``; ground truth from ``gt`` (an encounter with those
    robots) at each step's stamp, noted by :meth:`note` as the records come."""

    n_steps = None
    overlap = None

    def __init__(self, name: str, robot_ids: Sequence[str], gt: Any = None) -> None:
        self.name = name
        self.robots = [SimpleNamespace(robot_id=r) for r in robot_ids]
        self.gt = gt
        self._stamps: dict[int, float] = {}

    def note(self, step: int, stamp_s: float) -> None:
        self._stamps[int(step)] = float(stamp_s)

    def _pose(self, k: int, stamp_s: float) -> np.ndarray | None:
        rob = self.gt.robots[k]
        T = poses_at(np.array([stamp_s]), rob.stamps_s, rob.T_world_cam, GT_TOLERANCE_S, True, GT_MAX_GAP_S)[0]
        return T if np.all(np.isfinite(T)) else None

    def gt_T_cj_ci(self, t: int, i: int, j: int) -> np.ndarray | None:
        s = self._stamps.get(int(t))
        if self.gt is None or s is None:
            return None
        Ti, Tj = self._pose(i, s), self._pose(j, s)
        return None if Ti is None or Tj is None else paper_T_ij(Ti, Tj)

    def gt_viewing_angle(self, t: int, i: int, j: int) -> float:
        T = self.gt_T_cj_ci(t, i, j)
        return float("nan") if T is None else float(viewing_angle(T))
