"""The per-frame baselines (``sift-ransac``, ``aliked-lightglue``) as a step source of run folders.

Each pair is estimated from both robots' raw images at every evaluated step, independently of
every other step; the bytes counted are the JPEG image replies the exchange would take.
"""
from __future__ import annotations

from typing import Any, Callable, Iterator

import numpy as np

from ..geometry import se3_inverse
from ..records import STAGES, PairRecord, RobotRecord, StepResult

StepSource = Callable[[Any], Iterator[StepResult]]


def baseline_steps(method: str, seed: int, every: int = 1) -> tuple[dict, StepSource]:
    """A per-frame baseline's ``(run.json parameters, step source)``: each unordered pair once, the
    reverse direction is its inverse.

    The baseline sees both raw images at every step, i.e. every robot always
    sends its image; the bytes counted are the JPEG image replies it would take.
    """
    from ..baselines import build_baseline
    from ..baselines.base import PairEstimate
    from ..messages import ImageReply

    bl = build_baseline(method, seed=seed)

    def steps(encounter: Any) -> Iterator[StepResult]:
        robots = encounter.robots
        n = len(robots)
        for t in range(encounter.n_steps):
            imgs = [r.image(t) for r in robots]
            reply_bytes = [
                len(ImageReply.from_image(k, t, imgs[k], (r.intrinsics.fx, r.intrinsics.fy,
                                                           r.intrinsics.cx, r.intrinsics.cy)).encode())
                for k, r in enumerate(robots)
            ]
            pairs: dict[tuple[int, int], PairRecord] = {}
            timing = {k: {s: 0.0 for s in STAGES} for k in range(n)}
            evaluated = t % every == 0
            for i in range(n):
                for j in range(i + 1, n):
                    if evaluated:
                        est = bl.estimate(imgs[i], robots[i].intrinsics, imgs[j], robots[j].intrinsics)
                    else:  # independent per frame: a step nobody evaluates need not be computed
                        est = PairEstimate(None, "not-evaluated")
                    dt = float(sum(est.timings_s.values()))
                    timing[i]["backbone"] += dt
                    for (a, b, T) in ((i, j, est.T_cj_ci),
                                      (j, i, None if est.T_cj_ci is None else se3_inverse(est.T_cj_ci))):
                        pairs[(a, b)] = PairRecord(
                            step=t, stamp_s=float(robots[a].stamps_s[t]), ego=robots[a].robot_id,
                            other=robots[b].robot_id, gate_score=float("nan"), gate_open=True,
                            source="direct" if T is not None else "none", T_cj_ci=T,
                            reason=est.reason, bytes_pair=reply_bytes[b], direct_inliers=int(est.n_inliers),
                        )
            recs = [
                RobotRecord(step=t, stamp_s=float(r.stamps_s[t]), robot=r.robot_id,
                            T_odom_cam=np.full((4, 4), np.nan), scale=float("nan"), n_keyframes=0,
                            keyframe=False, bytes_sent={"reply": reply_bytes[k] * (n - 1)},
                            timings_s=timing[k])
                for k, r in enumerate(robots)
            ]
            yield StepResult(step=t, pairs=[pairs[p] for p in encounter.ordered_pairs()], robots=recs)

    return {"baseline": dict(bl.conf), "image_exchange": "always (JPEG quality 90)"}, steps
