"""Render a few frames of both synthetic worlds with their depth: figures/synth_examples.png.

Each row is one encounter at one step: robot r0's image and depth, then robot r1's
image and depth, titled with the ground-truth overlap ratio of (r0 -> r1) and the
relative viewing angle. Depth is shown in metres (black = no surface, e.g. sky).

    python -m lab.render_examples [--size 640x480] [--out figures/synth_examples.png]
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from cerpe.synth.groundtruth import overlap_ratio, viewing_angle_matrix  # noqa: E402
from cerpe.synth.renderer import render  # noqa: E402
from cerpe.synth.worlds import plan_encounter, quick_overlap  # noqa: E402

# (world, encounter index, show the step of highest (True) or lowest (False) r0->r1 overlap)
ROWS = [("cad-intersection", 0, True), ("cad-intersection", 1, False), ("cad-intersection", 2, False),
        ("cad-intersection", 3, True), ("indoor-team", 0, True), ("indoor-team", 1, False)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="640x480", help="image size WxH")
    ap.add_argument("--frames", type=int, default=30, help="frames per planned encounter")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("figures/synth_examples.png"))
    a = ap.parse_args()
    W, H = (int(x) for x in a.size.lower().split("x"))
    fig, axes = plt.subplots(len(ROWS), 4, figsize=(16, 3.0 * len(ROWS)))
    for r, (world, index, high) in enumerate(tqdm(ROWS, desc="examples")):
        plan = plan_encounter(world, a.seed, index, {"n_robots": 2 if world.startswith("cad") else 3,
                                                     "n_frames": a.frames, "fps": 10.0, "size": (W, H)})
        ov_quick = quick_overlap(plan)[:, 0, 1]
        t = int(np.argmax(ov_quick) if high else np.argmin(ov_quick))
        outs = [render(plan.faces_at(t, k), plan.T_world_cam[k, t], plan.intrinsics, plan.ctx) for k in (0, 1)]
        K = plan.intrinsics
        ov = overlap_ratio(outs[0].depth_m, K, plan.T_world_cam[0, t], outs[1].depth_m, K, plan.T_world_cam[1, t])
        va = np.rad2deg(viewing_angle_matrix(list(plan.T_world_cam[:2, t]))[0, 1])
        label = plan.meta.get("layout", "room")
        vmax = np.percentile(np.concatenate([o.depth_m[o.depth_m > 0] for o in outs]), 95)
        for k, o in enumerate(outs):
            axes[r, 2 * k].imshow(o.rgb)
            axes[r, 2 * k].set_title(f"{world} ({label}) r{k}, step {t}", fontsize=9)
            im = axes[r, 2 * k + 1].imshow(np.where(o.depth_m > 0, o.depth_m, np.nan), cmap="turbo", vmin=0, vmax=vmax)
            axes[r, 2 * k + 1].set_facecolor("black")
            axes[r, 2 * k + 1].set_title(f"depth r{k} [m]  overlap(r0->r1)={ov:.2f}, angle={va:.0f} deg", fontsize=9)
            fig.colorbar(im, ax=axes[r, 2 * k + 1], fraction=0.035)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    a.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = a.out.with_name(a.out.stem + ".tmp" + a.out.suffix)
    fig.savefig(tmp, dpi=70)
    os.replace(tmp, a.out)
    print(a.out)


if __name__ == "__main__":
    main()
