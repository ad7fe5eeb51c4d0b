"""A first minute with cerpe: one small encounter, CERPE and one baseline, a table and a picture.

What it does (`make demo` runs it with the defaults):

1. renders one encounter of two vehicles crossing a street junction (`cerpe synth
   cad-intersection`; images, metric depth and ground truth) into OUT/world/;
2. runs CERPE (Algorithm 1: descriptors on the wire, images only where the descriptor
   gate opens, direct estimates, the last one propagated with both robots' odometry)
   and a per-frame baseline that sees both images at every step (default
   ALIKED+LightGlue+RANSAC, the stand-in for the paper's SuperGlue row) with `cerpe
   run` into OUT/runs/<method>/;
3. evaluates both (`cerpe eval`) and prints one row per method, also written to
   OUT/summary.csv and OUT/summary.md: frames (ordered robot pairs x steps), estimates
   (direct and propagated), success % (frames with any estimate: the paper's measure),
   right % (frames with an estimate within 0.3 rad of the true rotation), mean e_rot
   (rad), mean e_pos (m, with the method's own scale; the baseline has none) and mean
   e_pos at the true distance;
4. draws OUT/demo.png: where each method puts the other vehicle on a bird's-eye view
   of the true paths, and the rotation and position errors step by step.

Every step is cached: a second run with the same arguments renders and runs nothing
(other arguments, or another version of the code, redo what changed). The defaults
give a scene large enough for the offline backbone to place the other vehicle's
image while the two see the same place; after that CERPE propagates, while the
baseline keeps answering from views that no longer overlap.

Examples:
  cerpe demo
  cerpe demo --seed 7 --out build/demo-s7
"""
from __future__ import annotations

import argparse
import dataclasses
import io
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from .atomicio import atomic_write_bytes, atomic_write_json, atomic_write_text, ensure_dir
from .errors import CerpeError


DEFAULT_OUT = Path("build") / "demo"
SETTING = "demo"
MARKER = "demo.json"  # written in OUT: a folder without it and not empty is not the demo's
FIGURE = "demo.png"
COLUMNS = ("method", "frames", "estimates", "direct", "propagated", "success %", "right %", "e_rot rad",
           "e_pos m", "e_pos m (true distance)")


class DemoError(CerpeError, ValueError):
    """A demo that cannot run: a bad option or an output folder that is not the demo's."""


@dataclass(frozen=True)
class DemoConfig:
    """The demo's encounter and methods.

    ``size`` is ``(width, height)`` in pixels, ``fps`` the frame rate (Hz): with ``frames``
    it sets how far the vehicles drive between steps. ``baseline``: a per-frame method of
    ``cerpe run`` (``aliked-lightglue`` or ``sift-ransac``).
    """

    world: str = "cad-intersection"
    seed: int = 3
    size: tuple[int, int] = (320, 240)
    frames: int = 24
    fps: float = 5.0
    baseline: str = "aliked-lightglue"

    def synth_conf(self) -> dict:
        """The generator arguments of :func:`cerpe.synth.generate_suite`."""
        return {"seed": int(self.seed), "n_encounters": 1, "n_frames": int(self.frames), "fps": float(self.fps),
                "size": tuple(int(v) for v in self.size), "n_robots": 2}

    def describe(self) -> str:
        w, h = self.size
        return (f"{self.world}, seed {self.seed}, 2 robots, {self.frames} frames at {self.fps:g} Hz, "
                f"{w}x{h} px")


@dataclass
class DemoResult:
    """What :func:`run_demo` made: the table (one row per method, :data:`COLUMNS`), its text, and paths."""

    table: pd.DataFrame
    text: str
    table_path: Path
    figure_path: Path
    run_dirs: dict[str, Path]


def _check(conf: DemoConfig) -> None:
    """Every option, before anything is written (a bad world argument raises the generator's own error)."""
    from .methods import BASELINE_METHODS
    from .synth.writer import full_conf

    if conf.baseline not in BASELINE_METHODS:
        raise DemoError(f"--baseline {conf.baseline!r}: choose one of {', '.join(BASELINE_METHODS)}")
    full_conf(conf.world, conf.synth_conf())


def _claim(out: Path, conf: DemoConfig) -> None:
    """Make ``out`` the demo's folder; refuse a folder with other content (the demo rewrites its files)."""
    ensure_dir(out, "--out", create=False)
    if out.is_dir() and not (out / MARKER).is_file() and any(out.iterdir()):
        raise DemoError(f"--out {out}: a folder that is not empty and not a demo folder (no {MARKER}); "
                        f"choose another --out")
    ensure_dir(out, "--out")
    atomic_write_json(out / MARKER, {"config": dataclasses.asdict(conf)})


def summary_table(frames: pd.DataFrame) -> pd.DataFrame:
    """One row per method of evaluated frames (:func:`cerpe.pipeline.evaluate.evaluate_runs`): the
    :data:`COLUMNS`; ``e_pos m`` is NaN for a method without metric scale."""
    from .pipeline.evaluate import summarise
    from .plotting import METHOD_ORDER, SHORT_LABELS

    s = summarise(frames, ["method"]).set_index("method")
    src = frames.groupby("method")["source"].value_counts().unstack(fill_value=0)
    rows = []
    order = ["cerpe"] + [m for m in METHOD_ORDER if m != "cerpe"]
    for m in [m for m in order if m in s.index] + [m for m in s.index if m not in order]:
        r = s.loc[m]
        rows.append({
            "method": SHORT_LABELS.get(m, m).replace("\n", " "), "frames": int(r["n_frames"]),
            "estimates": int(r["n_success"]), "direct": int(src.loc[m].get("direct", 0)),
            "propagated": int(src.loc[m].get("propagated", 0)), "success %": float(r["success_pct"]),
            "right %": float(r["right_pct"]), "e_rot rad": float(r["e_rot_rad"]),
            "e_pos m": float(r["e_pos_m"]), "e_pos m (true distance)": float(r["e_pos_gt_scale_m"]),
        })
    return pd.DataFrame(rows, columns=list(COLUMNS))


def table_cells(table: pd.DataFrame) -> list[list[str]]:
    """The table's rows as formatted strings (``--`` where a value does not exist)."""
    def fmt(v: object, digits: int) -> str:
        return "--" if not np.isfinite(float(v)) else f"{float(v):.{digits}f}"

    return [[str(r["method"]), str(r["frames"]), str(r["estimates"]), str(r["direct"]), str(r["propagated"]),
             fmt(r["success %"], 1), fmt(r["right %"], 1), fmt(r["e_rot rad"], 3), fmt(r["e_pos m"], 2),
             fmt(r["e_pos m (true distance)"], 2)] for _, r in table.iterrows()]


NOTE = ("frames: ordered robot pairs x steps. success: the method gave a pose (any pose, the paper's measure); "
        "right: a pose within 0.3 rad of the true rotation. Errors are means over the frames with a pose. "
        "e_pos m: with the method's own scale (the baseline has none: --); true distance: its direction "
        "scaled to the true distance.")


def _figure(frames: pd.DataFrame, manifest: Path, conf: DemoConfig, path: Path) -> None:
    from .pipeline.run import load_manifest_setting
    from .plot_encounter import encounter_figure

    enc = load_manifest_setting(manifest).encounters[0]
    ego, other = enc.robot_ids[0], enc.robot_ids[1]
    fig = encounter_figure(frames[frames["encounter"] == enc.name], {r.robot_id: r.T_world_cam for r in enc.robots},
                           ego, other, title=f"cerpe demo: {conf.describe()}")
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def run_demo(out: Path | str = DEFAULT_OUT, conf: DemoConfig = DemoConfig(), progress: bool = True) -> DemoResult:
    """Render (or reuse) the encounter, run (or reuse) CERPE and the baseline, write the table and the picture."""
    from .pipeline.evaluate import evaluate_runs
    from .pipeline.run import run_method
    from .synth import generate_suite

    _check(conf)
    out = Path(out)
    _claim(out, conf)
    # force / overwrite: these folders are the demo's own; same arguments and code reuse them as they are
    manifest = generate_suite(conf.world, out / "world", conf.synth_conf(), force=True, progress=progress,
                              setting=SETTING)
    runs = {m: run_method(manifest, m, out / "runs" / m, overwrite=True, progress=progress)
            for m in ("cerpe", conf.baseline)}
    frames, _ = evaluate_runs(list(runs.values()))
    table = summary_table(frames)
    cells = table_cells(table)
    from .pipeline.textfmt import md_table, text_table

    atomic_write_text(out / "summary.csv", table.to_csv(index=False))
    atomic_write_text(out / "summary.md", md_table(COLUMNS, cells) + "\n\n" + NOTE + "\n")
    _figure(frames, manifest, conf, out / FIGURE)
    return DemoResult(table=table, text=text_table(COLUMNS, cells, left=1), table_path=out / "summary.csv",
                      figure_path=out / FIGURE, run_dirs=runs)


# --------------------------------------------------------------------------- CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    from .synth.cli import _size  # `cerpe synth --size`'s parser: WxH

    d = DemoConfig()
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"demo folder (default {DEFAULT_OUT})")
    p.add_argument("--world", choices=("cad-intersection", "indoor-team"), default=d.world,
                   help=f"synthetic world (default {d.world}; indoor-team: two of the ground robots)")
    p.add_argument("--seed", type=int, default=d.seed, help=f"world seed (default {d.seed})")
    p.add_argument("--size", type=_size, default=d.size, help="image size WxH (default %dx%d)" % d.size)
    p.add_argument("--frames", type=int, default=d.frames, help=f"steps of the encounter (default {d.frames})")
    p.add_argument("--fps", type=float, default=d.fps, help=f"frame rate in Hz (default {d.fps:g})")
    p.add_argument("--baseline", default=d.baseline,
                   help=f"per-frame baseline beside CERPE: aliked-lightglue or sift-ransac (default {d.baseline})")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")


def main(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    conf = DemoConfig(world=args.world, seed=args.seed, size=tuple(args.size), frames=args.frames, fps=args.fps,
                      baseline=args.baseline)
    print(f"cerpe demo: {conf.describe()} -> {args.out}", flush=True)
    res = run_demo(args.out, conf, progress=not args.no_progress)
    print()
    print(res.text)
    print()
    print(NOTE)
    print(f"table: {res.table_path}")
    print(f"picture: {res.figure_path}")
    print(f"done in {time.perf_counter() - t0:.0f} s")
    return 0
