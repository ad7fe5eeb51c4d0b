"""Image reply codecs: bytes against the direct estimate's accuracy, on development pairs.

Each case is an ego robot's RGB-D frame and a co-visible collaborator frame (ground-truth
overlap >= --min-overlap) of a development set: the real SUN3D fragments (fragment 1 ego,
fragment 2 collaborator), TUM fr1/xyz (frames 0-4 ego, 5-9 collaborator) and synthetic
suites of development seeds (`cerpe dev` renders; seed 0 refused). For every codec setting
the collaborator image goes through a real ImageReply frame (cerpe.messages: codec,
quality, downsizing with intrinsics scaled), is decoded as a robot decodes it
(cerpe.algorithm.frames.received_view), and the offline backbone registers it against the
ego frame in one pass ([ego, collaborator]); the direct estimate T_cj_ci is compared with
ground truth. Prints per setting: mean reply frame bytes, placed %, median and mean
rotation error (deg) and translation error (m) over the cases every setting placed, and
"correct" % (rotation < 5 deg and translation < 0.25 m) over all cases.

    python -m lab.reply_codecs                       # SUN3D + fr1/xyz + synthetic seed 2001, 12 cases each
    python -m lab.reply_codecs --settings jpeg:90:1 webp:60:0.5 --cases 30
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_SETTINGS = ["jpeg:90:1", "jpeg:75:1", "jpeg:50:1", "jpeg:90:0.75", "jpeg:75:0.75", "jpeg:90:0.5",
                    "jpeg:75:0.5", "jpeg:50:0.5", "webp:90:1", "webp:75:1", "webp:50:1", "webp:75:0.75",
                    "webp:90:0.5", "webp:75:0.5", "webp:50:0.5"]


def _args(argv):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--settings", nargs="+", default=DEFAULT_SETTINGS, help="CODEC:QUALITY:SCALE")
    ap.add_argument("--synth-seeds", type=int, nargs="*", default=[2001])
    ap.add_argument("--real", nargs="*", default=["dev-sun3d-two-fragments", "dev-tum-fr1-xyz"],
                    help="real development manifests by name (datasets_manifest/<name>.yaml)")
    ap.add_argument("--dev-out", type=Path, default=ROOT / "build" / "dev")
    ap.add_argument("--cases", type=int, default=12, help="cases per set (evenly spread over its co-visible pairs)")
    ap.add_argument("--min-overlap", type=float, default=0.2, help="co-visible: overlap >= this both ways")
    ap.add_argument("--csv", type=Path, default=None, help="write every case's result here")
    return ap.parse_args(argv)


def _cases(setting, n: int, min_overlap: float):
    """``(encounter, ego robot, collaborator robot, t, u)`` of co-visible cross-robot pairs, ``n`` spread evenly."""
    from cerpe.synth.groundtruth import overlap_ratio

    out = []
    for enc in setting.encounters:
        steps = range(0, enc.n_steps, max(1, enc.n_steps // 12))
        for i, j in enc.ordered_pairs():
            ri, rj = enc.robots[i], enc.robots[j]
            for t in steps:
                for u in steps:
                    if (ri.depth is None or rj.depth is None or not ri.has_gt(t) or not rj.has_gt(u)):
                        continue
                    o = min(overlap_ratio(ri.depth_m(t), ri.intrinsics, ri.T_world_cam[t], rj.depth_m(u),
                                          rj.intrinsics, rj.T_world_cam[u]),
                            overlap_ratio(rj.depth_m(u), rj.intrinsics, rj.T_world_cam[u], ri.depth_m(t),
                                          ri.intrinsics, ri.T_world_cam[t]))
                    if o >= min_overlap:
                        out.append((enc, i, j, t, u))
    if len(out) > n:
        out = [out[k] for k in np.linspace(0, len(out) - 1, n).round().astype(int)]
    return out


def _rot_deg(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def main(argv=None) -> int:
    a = _args(argv)
    import pandas as pd

    from cerpe.algorithm.frames import received_view
    from cerpe.algorithm.poses import direct_relative, registered_relative
    from cerpe.backbones.build import build_plugins
    from cerpe.datasets import load_setting
    from cerpe.geometry import se3_inverse
    from cerpe.messages import ImageReply, decode
    from cerpe.pipeline.dev import PAPER_SEED, synthetic_set
    from cerpe.protocols import View
    from cerpe.synth import SUITES

    settings = []
    for s in a.settings:
        codec, q, sc = s.split(":")
        settings.append((codec, int(q), float(sc)))
    manifests = []
    for seed in a.synth_seeds:
        if seed == PAPER_SEED:
            raise SystemExit("reply_codecs: seed 0 is the paper-default suite (test data)")
        manifests += [synthetic_set(st, seed, "dev", a.dev_out, progress=False).manifest for st in SUITES["paper-default"]]
    manifests += [ROOT / "datasets_manifest" / f"{n}.yaml" for n in a.real
                  if (ROOT / "datasets_manifest" / f"{n}.yaml").is_file()]
    backbone = build_plugins().backbone
    rows = []
    t0 = time.perf_counter()
    for man in manifests:
        setting = load_setting(man)
        if not setting.encounters or setting.encounters[0].robots[0].depth is None:
            print(f"{setting.name}: no depth; skipped", file=sys.stderr)
            continue
        cases = _cases(setting, a.cases, a.min_overlap)
        print(f"{setting.name}: {len(cases)} cases", file=sys.stderr)
        for enc, i, j, t, u in cases:
            ri, rj = enc.robots[i], enc.robots[j]
            ego = View((f"{enc.name}/{ri.robot_id}", t), ri.image(t), ri.intrinsics, ri.depth_m(t))
            gt = se3_inverse(rj.T_world_cam[u]) @ ri.T_world_cam[t]  # T_cj_ci
            Kj = rj.intrinsics
            for codec, q, sc in settings:
                frame = ImageReply.from_image(j, u, rj.image(u), (Kj.fx, Kj.fy, Kj.cx, Kj.cy), quality=q,
                                              codec=codec, scale=sc).encode()
                view, fault = received_view(f"{enc.name}/{rj.robot_id}/{codec}{q}@{sc}", decode(frame))
                row = {"set": setting.name, "case": f"{enc.name}:{ri.robot_id}{t}-{rj.robot_id}{u}",
                       "setting": f"{codec}:{q}:{sc}", "bytes": len(frame), "placed": False,
                       "rot_deg": np.nan, "trans_m": np.nan}
                if view is not None:
                    out = backbone.infer([ego, view])
                    regs = [r for r in out.registrations.get(1, ()) if r.via == 0]
                    T = (registered_relative(regs[0].T_via_cam, np.eye(4), 1.0) if regs else
                         direct_relative(out.T_frame_cam[0], out.T_frame_cam[1], 1.0)
                         if out.valid[0] and out.valid[1] else None)
                    if T is not None:
                        row.update(placed=True, rot_deg=_rot_deg(T[:3, :3].T @ gt[:3, :3]),
                                   trans_m=float(np.linalg.norm(T[:3, 3] - gt[:3, 3])))
                rows.append(row)
    df = pd.DataFrame(rows)
    if a.csv:
        df.to_csv(a.csv, index=False)
    df["correct"] = (df["rot_deg"] < 5) & (df["trans_m"] < 0.25)
    for name, sub in [("all sets", df)] + list(df.groupby("set")):
        tab = sub.groupby("setting", sort=False).agg(bytes=("bytes", "mean"), placed_pct=("placed", "mean"),
                                                     correct_pct=("correct", "mean"), rot_med=("rot_deg", "median"),
                                                     rot_mean=("rot_deg", "mean"), trans_med=("trans_m", "median"),
                                                     trans_mean=("trans_m", "mean"))
        tab[["placed_pct", "correct_pct"]] *= 100
        print(f"\n{name}: {sub['case'].nunique()} cases (errors in deg / m over each setting's placed cases)")
        print(tab.to_string(float_format=lambda v: f"{v:.3f}"))
    print(f"\nreply_codecs: {len(df)} registrations in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
