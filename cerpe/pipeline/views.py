"""The paper's CERPE rows as views of one pass run with propagation and the pose graph.

Propagation and the pose graph feed nothing back (anchors come only from direct estimates; the
gate, memory, scale and odometry never read a propagated pose or the graph), so ``cerpe`` is the
pass's switch records (:attr:`~cerpe.records.PairRecord.switch`), ``cerpe-wo-em`` those with the
propagated estimates removed, and ``cerpe-graph`` the pass itself
(``tests/test_pipeline_woem.py`` checks each view against a real run of its configuration).
"""
from __future__ import annotations

import dataclasses

from ..reasons import join, split
from ..records import StepResult


def switch_view(res: StepResult) -> StepResult:
    """The paper's CERPE (``backend="switch"``) view of a step run with ``backend="graph"``.

    Pair estimates come from :attr:`PairRecord.switch`; the graph's degradations and
    its stage time are removed. A step without switch records is returned as it is.
    """
    if not any(p.switch is not None for p in res.pairs):
        return res
    pairs = []
    for p in res.pairs:
        if p.switch is not None:
            source, T, reason, anchor_step = p.switch
            p = dataclasses.replace(p, source=source, T_cj_ci=T, reason=reason, anchor_step=anchor_step,
                                    cov=None, switch=None)
        pairs.append(p)
    robots = [dataclasses.replace(r, timings_s={**r.timings_s, "graph": 0.0},
                                  degradations=[d for d in r.degradations if not d.startswith("graph:")])
              for r in res.robots]
    return StepResult(step=res.step, pairs=pairs, robots=robots)


def without_propagation(res: StepResult) -> StepResult:
    """The "w/o EM" view of a full CERPE step: propagated estimates become ``none``."""
    pairs = []
    for p in res.pairs:
        # reasons that only a propagated (or no longer propagated) estimate has
        carried = ("stale-pose", "no-anchor", "no-pose-of-other", "unverified", "unverified-expired")
        if p.source == "propagated" or (p.source == "none" and any(r in carried for r in split(p.reason))):
            reason = join(*(r for r in split(p.reason) if r not in carried)) or ("gate-closed" if not p.gate_open else "")
            p = dataclasses.replace(p, source="none", T_cj_ci=None, anchor_step=-1, reason=reason)
        pairs.append(p)
    robots = [dataclasses.replace(r, timings_s={**r.timings_s, "propagation": 0.0},
                                  degradations=[d for d in r.degradations if d != "pose:stale"])
              for r in res.robots]
    return StepResult(step=res.step, pairs=pairs, robots=robots)
