"""`cerpe bench`'s timing of the pose-graph back end of ``cerpe-graph`` (our extension): one graph
per peer and robot, fed a simulated stream (:mod:`cerpe.algorithm.graph_sim`), since walking the
backbone for a minute of steps per robot would take far longer than the graph itself.
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np

from .bench_walk import median_p90

GRAPH_TARGET_MS = 10.0  # target of the graph update per robot-step, median (ms)


def graph_latency(n_robots: int, seconds: float = 60.0, rate_hz: float = 10.0, direct_share: float = 0.5,
                  seed: int = 0) -> dict[str, Any]:
    """Time :meth:`~cerpe.algorithm.graph.PairGraph.step` per robot-step over a simulated encounter.

    Each robot keeps one graph per peer (``n_robots - 1``) with the default configuration;
    a robot-step's time is the sum over its graphs. Direct estimates come on a random
    ``direct_share`` of the steps with the graph's own noise levels, 5 % of them 0.5 rad wrong.
    """
    from ..algorithm.graph import GRAPH_MODEL, DirectEstimate, PairGraph
    from ..algorithm.graph_sim import perturb, simulate_pair

    conf = GRAPH_MODEL
    n_steps = max(int(round(seconds * rate_hz)), 2)
    rng = np.random.default_rng(seed)
    share = float(np.clip(direct_share if np.isfinite(direct_share) else 0.5, 0.02, 1.0))
    streams = []
    for k in range(n_robots * (n_robots - 1)):
        steps = [0] + [t for t in range(1, n_steps) if rng.random() < share]
        s = simulate_pair(seed + k, n_steps, speed_m=1.0 / rate_hz, odo_rot=conf.odo_rot_per_step,
                          odo_trans=conf.odo_trans_per_step, direct_steps=steps, direct_rot=conf.direct_rot_rad,
                          direct_trans=conf.direct_trans_m)
        for t in steps:
            if rng.random() < 0.05:
                s.direct[t] = perturb(rng, s.truth[t], 0.5 / np.sqrt(3), 0.5)
        streams.append((PairGraph(conf), s))
    per_robot: list[float] = []
    nodes = 0
    for t in range(n_steps):
        for r in range(n_robots):
            t0 = time.perf_counter()
            for g, s in streams[r * (n_robots - 1):(r + 1) * (n_robots - 1)]:
                d = DirectEstimate(t, s.direct[t]) if t in s.direct else None
                g.step(t, s.X_i[t], s.X_j[t], t, d)
            per_robot.append(1000 * (time.perf_counter() - t0))
    nodes = sum(g.n_nodes for g, _ in streams)
    return {"n_robots": n_robots, "seconds": float(seconds), "steps": n_steps, "direct_share": share,
            "nodes": int(nodes), "update_ms": median_p90(per_robot), "target_ms": GRAPH_TARGET_MS}
