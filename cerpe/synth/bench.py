"""Rendering speed of the synthetic worlds (prints figures; not a test).

    python -m cerpe.synth.bench [--size 640x480] [--frames 12]

Per world: planning time, then per rendered frame wall and CPU milliseconds
(RGB + exact depth, one process) and frames per second, plus the overlap
ground truth per step. On a shared machine compare CPU time, not wall time.
"""
from __future__ import annotations

import argparse
import time

from .groundtruth import overlap_matrix
from .renderer import render
from .worlds import WORLDS, plan_encounter


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--frames", type=int, default=12, help="steps rendered per world (every robot)")
    a = ap.parse_args(argv)
    W, H = (int(x) for x in a.size.lower().split("x"))
    for world in WORLDS:
        n = 2 if world == "cad-intersection" else 3
        w0, c0 = time.perf_counter(), time.process_time()
        plan = plan_encounter(world, 0, 0, {"n_robots": n, "n_frames": max(a.frames, 12), "fps": 10.0, "size": (W, H)})
        print(f"{world}: plan {time.perf_counter() - w0:.2f} s wall ({time.process_time() - c0:.2f} s CPU), "
              f"{len(plan.static)} static faces")
        w0, c0, frames, ov_s = time.perf_counter(), time.process_time(), 0, 0.0
        for t in range(a.frames):
            outs = [render(plan.faces_at(t, k), plan.T_world_cam[k, t], plan.intrinsics, plan.ctx) for k in range(n)]
            frames += n
            o0 = time.process_time()
            overlap_matrix([o.depth_m for o in outs], [plan.intrinsics] * n, list(plan.T_world_cam[:, t]), 4)
            ov_s += time.process_time() - o0
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        print(f"  {frames} frames {W}x{H}: {1000 * wall / frames:.0f} ms/frame wall, {1000 * (cpu - ov_s) / frames:.0f} ms/frame "
              f"CPU render, {1000 * ov_s / frames:.1f} ms/frame CPU overlap -> {frames / wall:.2f} frames/s (one process)")


if __name__ == "__main__":
    main()
