"""Wide-baseline pairs from the development sets, end to end: how many collaborator views a method places.

The held-out failure this watches: real pairs with a large viewpoint change, where the
collaborator image is placed (or not) from one exchange, with no sequence to verify it. This
builds such pairs from ``../shared/data`` (development data only), writes them in the
``pairs`` adapter's format (SuperGlue / LoFTR list) with a manifest under ``--out`` (never
committed: they carry ground truth derived from the shared data), runs each method with
``cerpe run`` (cached and resumable like any run folder) and prints per viewing-angle band:
pairs x 2 directions, placed, right (rotation error < 0.3 rad, :data:`cerpe.pipeline.evaluate.RIGHT_ROT_RAD`),
wrong, and the median rotation error of the placed ones.

* ``fr3``: every pair of the 16 posed TUM fr3 office frames whose viewing directions are
  ``--min-deg`` .. ``--max-deg`` apart (RGB only: the collaborator is placed by the essential
  matrix, at ground-truth scale);
* ``sun3d``: every ``--stride``-th frame of fragment 1 against every ``--stride``-th of fragment 2
  (RGB-D, depth in millimetres; a repetitive room, coarse cross-fragment ground truth);
* ``synth``: a synthetic development suite (``--suite``, a ``cerpe synth`` folder such as
  ``build/dev/synth/dev/indoor-team-seed2001``; never the paper-default seed 0): every ``--every``-th
  frame of each robot against every ``--every``-th of each other robot (also places one saw before
  the other), viewing directions ``--min-deg`` .. ``--max-deg`` apart, each camera seeing at least
  ``--min-overlap`` of the other's surface (RGB-D: the wide-baseline case with depth, which the real
  development data lacks).

    python -m lab.wide_pairs --set fr3 --methods cerpe aliked-lightglue
    python -m lab.wide_pairs --set sun3d --stride 5
    python -m lab.wide_pairs --set synth --suite build/dev/synth/dev/indoor-team-seed2001 --max-deg 170
"""
from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np

from cerpe.geometry import rotation_angle, se3_from_tq_xyzw, se3_inverse

ROOT = Path(__file__).resolve().parents[1]

DATA = ROOT.parent / "shared" / "data"
K_FR3 = "535.4 0 320.1 0 539.2 247.6 0 0 1"
K_SUN3D = "585 0 320 0 585 240 0 0 1"
BANDS_DEG = (30, 40, 50, 60, 90, 180)


def fr3_pairs(min_deg: float, max_deg: float) -> tuple[Path, list[tuple[str, str, np.ndarray]]]:
    root = DATA / "tum-fr3-office"
    poses = {}
    for line in (root / "groundtruth.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            v = line.split()
            poses[v[0]] = se3_from_tq_xyzw(np.array(v[1:4], float), np.array(v[4:8], float))
    out = []
    for a, b in itertools.combinations(sorted(poses), 2):
        T_b_a = se3_inverse(poses[b]) @ poses[a]  # T_0to1: points of camera a into camera b
        if min_deg <= np.degrees(rotation_angle(T_b_a[:3, :3])) <= max_deg:
            out.append((f"rgb/{a}.png", f"rgb/{b}.png", T_b_a))
    return root, out


def sun3d_pairs(stride: int, min_deg: float, max_deg: float) -> tuple[Path, list[tuple[str, str, np.ndarray]]]:
    root = DATA / "sun3d-two-fragments"

    def load(k: int) -> dict[str, np.ndarray]:
        poses = {}
        for line in (root / f"poses_c2w_fragment-{k}.txt").read_text().splitlines():
            if line.strip() and not line.startswith("#"):
                v = line.split()
                T = np.eye(4)
                T[:3, :] = np.array(v[1:13], float).reshape(3, 4)
                poses[f"fragment-{k}/{v[0]}"] = T
        return poses

    one, two = load(1), load(2)
    out = []
    for a in sorted(one)[::stride]:
        for b in sorted(two)[::stride]:
            T_b_a = se3_inverse(two[b]) @ one[a]
            if min_deg <= np.degrees(rotation_angle(T_b_a[:3, :3])) <= max_deg:
                out.append((f"{a}.color.png", f"{b}.color.png", T_b_a))
    return root, out


def synth_pairs(suite: Path, every: int, min_deg: float, max_deg: float,
                min_overlap: float) -> tuple[Path, list[tuple[str, str, np.ndarray]], str]:
    """Pairs of two robots' frames of a synthetic development suite (a ``cerpe synth`` folder, RGB-D, read
    through its manifest): every ``every``-th step of each robot against every ``every``-th of the other
    (so also a place one robot saw before the other), viewing directions ``min_deg`` .. ``max_deg`` apart,
    each camera seeing at least ``min_overlap`` of the other's surface (depth and ground truth, as
    ``cerpe synth``)."""
    from cerpe.pipeline.setting import load_manifest_setting
    from cerpe.scene import load_depth_m
    from cerpe.synth.groundtruth import overlap_ratio

    out, K = [], ""
    for enc in load_manifest_setting(suite / "manifest.yaml").encounters:
        frames = {}
        for rs in enc.robots:
            i = rs.intrinsics
            K = K or f"{i.fx} 0 {i.cx} 0 {i.fy} {i.cy} 0 0 1"
            image = [Path(getattr(ref, "path", ref)).relative_to(suite) for ref in rs.images]  # ImageFile or Path
            frames[rs.robot_id] = [(image[t], rs.T_world_cam[t], load_depth_m(rs.depth[t], rs.depth_units_per_m), i)
                                   for t in range(0, len(rs.stamps_s), every)]
        for a, b in itertools.combinations(sorted(frames), 2):
            for (pa, Ta, Da, Ka), (pb, Tb, Db, Kb) in itertools.product(frames[a], frames[b]):
                T_b_a = se3_inverse(Tb) @ Ta
                if not min_deg <= np.degrees(rotation_angle(T_b_a[:3, :3])) <= max_deg:
                    continue
                seen = min(overlap_ratio(Da, Ka, Ta, Db, Kb, Tb, 8), overlap_ratio(Db, Kb, Tb, Da, Ka, Ta, 8))
                if seen >= min_overlap:
                    out.append((str(pa), str(pb), T_b_a))
    return suite, out, K


def write_set(name: str, root: Path, pairs: list, K: str, out: Path, depth: bool,
              replace: str = "[[color, depth]]") -> Path:
    out.mkdir(parents=True, exist_ok=True)
    lines = [f"{a} {b} 0 0 {K} {K} " + " ".join(f"{x:.9f}" for x in T.ravel()) for a, b, T in pairs]
    (out / "pairs.txt").write_text("\n".join(lines) + "\n")
    man = [f"name: {name}", "adapter: pairs", f"data_root: {root}", f"pairs: {out / 'pairs.txt'}", "images: .",
           "evaluation: {every: 1}"]
    man += [f"depth: {{replace: {replace}, units_per_m: 1000}}", "metric_depth: dataset", "covisibility: auto"] \
        if depth else ["metric_depth: none"]
    path = out / f"{name}.yaml"
    path.write_text("\n".join(man) + "\n")
    return path


def table(run_dir: Path) -> str:
    import pandas as pd

    from cerpe.pipeline.evaluate import RIGHT_ROT_RAD, frame_errors, load_run

    run = load_run(run_dir)
    f = frame_errors(run.steps, True, run.every)
    f["band"] = pd.cut(np.degrees(f["view_angle_gt"]), list(BANDS_DEG))
    rows = []
    for band, g in f.groupby("band", observed=True):
        e = g["e_rot_rad"].dropna()
        rows.append(f"  {str(band):>10}  {len(g):4d}  {len(e):6d}  {int((e < RIGHT_ROT_RAD).sum()):5d}  "
                    f"{int((e >= RIGHT_ROT_RAD).sum()):5d}  {e.median() if len(e) else float('nan'):8.3f}")
    e = f["e_rot_rad"].dropna()
    rows.append(f"  {'all':>10}  {len(f):4d}  {len(e):6d}  {int((e < RIGHT_ROT_RAD).sum()):5d}  "
                f"{int((e >= RIGHT_ROT_RAD).sum()):5d}  {e.median() if len(e) else float('nan'):8.3f}")
    return "\n".join([f"  {'deg':>10}  {'n':>4}  {'placed':>6}  {'right':>5}  {'wrong':>5}  {'med rad':>8}"] + rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--set", choices=("fr3", "sun3d", "synth"), default="fr3")
    ap.add_argument("--suite", type=Path, help="synth: a synthetic development suite folder (never paper-default)")
    ap.add_argument("--every", type=int, default=3, help="synth: every N-th step")
    ap.add_argument("--min-overlap", type=float, default=0.2, help="synth: least overlap, both ways")
    ap.add_argument("--min-deg", type=float, default=30.0, help="smallest angle between the two viewing directions")
    ap.add_argument("--max-deg", type=float, default=75.0, help="largest angle between the two viewing directions")
    ap.add_argument("--stride", type=int, default=5, help="sun3d: every N-th frame of each fragment")
    ap.add_argument("--methods", nargs="+", default=["cerpe", "aliked-lightglue"])
    ap.add_argument("--out", type=Path, default=ROOT / "build" / "dev" / "wide-pairs")
    args = ap.parse_args(argv)
    if args.set == "synth" and (args.suite is None or not (args.suite / "manifest.yaml").is_file()):
        print(f"wide_pairs: --set synth needs --suite, a `cerpe synth` folder (got {args.suite})")
        return 2
    if args.set == "synth":
        from cerpe.pipeline.dev import PAPER_SEED

        try:
            seed = json.loads((args.suite / "meta.json").read_text())["key"]["args"]["seed"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            print(f"wide_pairs: {args.suite / 'meta.json'}: cannot read the suite's seed (key.args.seed): "
                  f"{type(exc).__name__}: {exc}")
            return 2
        if seed == PAPER_SEED:
            print(f"wide_pairs: {args.suite} was rendered with seed {PAPER_SEED}, the paper-default test suite: "
                  f"not for development")
            return 2
    if args.set != "synth" and not DATA.is_dir():
        print(f"wide_pairs: no development data at {DATA}: nothing to do")
        return 0
    if args.set == "fr3":
        root, pairs = fr3_pairs(args.min_deg, args.max_deg)
        name, K, depth = "dev-fr3-wide-pairs", K_FR3, False
    elif args.set == "sun3d":
        root, pairs = sun3d_pairs(max(1, args.stride), args.min_deg, args.max_deg)
        name, K, depth = "dev-sun3d-wide-pairs", K_SUN3D, True
    else:
        root, pairs, K = synth_pairs(args.suite.resolve(), max(1, args.every), args.min_deg, args.max_deg,
                                     args.min_overlap)
        name, depth = f"dev-{args.suite.name}-wide-pairs", True
    if not pairs:
        print(f"wide_pairs: no {args.set} pair between {args.min_deg} and {args.max_deg} deg")
        return 1
    man = write_set(name, root, pairs, K, args.out / name, depth,
                    "[[/rgb/, /depth/]]" if args.set == "synth" else "[[color, depth]]")
    print(f"{name}: {len(pairs)} pairs ({args.min_deg:g}-{args.max_deg:g} deg), manifest {man}")
    from cerpe.pipeline.run import run_method

    for m in args.methods:
        run_dir = run_method(man, m, args.out / name / m, overwrite=True, progress=False)
        print(f"\n{m} ({run_dir}):\n{table(run_dir)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
