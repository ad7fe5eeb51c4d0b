"""Metric translation from depth + PnP on real RGB-D against ground truth.

Between frames ``ref`` (its depth is the prior) and ``cur`` of one sequence: the pose
``T_cur_ref`` from (a) XFeat mutual-NN matches + P3P RANSAC on the reference frame's
depth at its keypoints, and (b) the offline backbone itself (P3P, motion vote, dense
RGB-D refinement), compared with the ground truth; and (c) ``gt-vs-depth``: the factor on the
ground-truth translation that makes the two depth maps agree best (no images, no CERPE;
1.0 when ground truth and depth agree on the metre). Figures per variant: median
``|t|/|t_gt|`` (length ratio), median ``t . t_gt / |t_gt|^2`` (the part along the true
motion), median translation error (mm) and rotation error (deg), over pairs whose true
baseline is at least ``--min-baseline`` metres.

Variants on TUM fr1/xyz (distorted lens, depth registered to colour, 5000 units/m):
the images as stored with the README's pinhole intrinsics (what the dataset adapter
hands CERPE today), undistorted colour and depth (same lens: depth is registered), and
TUM's published fr1 depth correction (x1.035). Depth at keypoints: ``keypoint_depths``
(3x3 median, edge test; the backbone's) or the nearest pixel. SUN3D (undistorted, depth
used by its own SfM poses) and a synthetic suite (exact depth) are controls; the synthetic
frames are also run through the fr1 lens and a barrel lens (k1 = -0.2) that nobody undoes.

    python -m lab.scale --synth build/dev-synth/indoor-s7/manifest.yaml

``--runs DIR`` instead measures the odometry of finished CERPE runs (``cerpe dev``'s
``DIR/runs/<set>/cerpe/``): per set, the predicted / true length of every step of every
robot (``robots.csv``'s ``T_odom_cam`` against the manifest's ground truth): median, 10th
and 90th percentile, the steps outside [0.5, 2], and the steps held by the odometry's
step-length rule (``ego:step-held``)::

    python -m lab.scale --runs build/dev
"""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from cerpe.backbones.config import OfflineConfig
from cerpe.backbones.offline import OfflineGeometryBackbone, keypoint_depths, match_mnn
from cerpe.backbones.xfeat import XFeatEncoder
from cerpe.protocols import View
from cerpe.scene import CameraIntrinsics

from .sets import DATA, DIST_FR1, Frame, fr1_frames, gt_T_b_a, sun3d_fragment, transfer_depth


def pnp_pose(enc: XFeatEncoder, ref: Frame, cur: Frame, sampling: str, px: float = 2.0) -> np.ndarray | None:
    """``T_cur_ref`` by P3P RANSAC of ``cur``'s keypoints on ``ref``'s depth (None: < 25 inliers)."""
    import poselib

    fr, fc = enc.encode_image(ref.image), enc.encode_image(cur.image)
    m = match_mnn(fr.descriptors, fc.descriptors)
    uv_r, uv_c = fr.keypoints[m[:, 0]].astype(np.float64), fc.keypoints[m[:, 1]].astype(np.float64)
    if sampling == "keypoint_depths":
        z = keypoint_depths(uv_r, ref.depth_m, ref.image.shape[:2], 0.2)
    else:  # the pixel under the keypoint
        u = np.clip(np.round(uv_r[:, 0]).astype(int), 0, ref.depth_m.shape[1] - 1)
        v = np.clip(np.round(uv_r[:, 1]).astype(int), 0, ref.depth_m.shape[0] - 1)
        z = ref.depth_m[v, u].astype(np.float64)
    ok = z > 0
    if ok.sum() < 25:
        return None
    K = ref.K.K
    X = np.column_stack([(uv_r[ok, 0] - K[0, 2]) / K[0, 0], (uv_r[ok, 1] - K[1, 2]) / K[1, 1], np.ones(ok.sum())]) * z[ok, None]
    Kc = cur.K
    cam = {"model": "PINHOLE", "width": int(Kc.width), "height": int(Kc.height),
           "params": [float(Kc.fx), float(Kc.fy), float(Kc.cx), float(Kc.cy)]}
    pose, info = poselib.estimate_absolute_pose(uv_c[ok], X, cam, {"max_reproj_error": px, "min_iterations": 100,
                                                                   "max_iterations": 4000}, {})
    if np.sum(info["inliers"]) < 25:
        return None
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = pose.R, pose.t
    return T


def backbone_pose(bb: OfflineGeometryBackbone, ref: Frame, cur: Frame) -> np.ndarray | None:
    """``T_cur_ref`` from one offline-backbone pass over ``[cur, ref]`` (both with depth priors)."""
    bb.clear_caches()
    out = bb.infer([View(("cur", cur.key), cur.image, cur.K, cur.depth_m),
                    View(("ref", ref.key), ref.image, ref.K, ref.depth_m)])
    if not out.valid[1]:
        return None
    return np.linalg.inv(out.T_frame_cam[0]) @ out.T_frame_cam[1]


def distort_frame(f: Frame, dist: np.ndarray) -> Frame:
    """``f`` as a lens with OpenCV distortion ``dist`` (k1 k2 p1 p2 k3) would have seen it, colour
    and registered depth alike, keeping the pinhole intrinsics: what an adapter that ignores the
    lens hands CERPE."""
    import cv2

    H, W = f.image.shape[:2]
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    src = cv2.undistortPoints(np.stack([u.ravel(), v.ravel()], 1)[:, None], f.K.K, dist, P=f.K.K).reshape(H, W, 2)
    mx, my = np.ascontiguousarray(src[..., 0]), np.ascontiguousarray(src[..., 1])
    return dataclasses.replace(f, image=cv2.remap(f.image, mx, my, cv2.INTER_LINEAR),
                               depth_m=cv2.remap(f.depth_m, mx, my, cv2.INTER_NEAREST))


def stats(pairs: list[tuple[np.ndarray | None, np.ndarray]], min_baseline: float) -> dict[str, float]:
    ratio, along, err, rot = [], [], [], []
    n_all = 0
    for T, T_gt in pairs:
        tg = T_gt[:3, 3]
        if np.linalg.norm(tg) < min_baseline:
            continue
        n_all += 1
        if T is None:
            continue
        t = T[:3, 3]
        ratio.append(np.linalg.norm(t) / np.linalg.norm(tg))
        along.append(t @ tg / (tg @ tg))
        err.append(1e3 * np.linalg.norm(t - tg))
        R = T[:3, :3].T @ T_gt[:3, :3]
        rot.append(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
    med = lambda x: float(np.median(x)) if x else float("nan")  # noqa: E731
    return {"n": len(ratio), "of": n_all, "ratio": med(ratio), "along": med(along), "err_mm": med(err), "rot_deg": med(rot),
            "ratio_q25": float(np.quantile(ratio, 0.25)) if ratio else float("nan"),
            "ratio_q75": float(np.quantile(ratio, 0.75)) if ratio else float("nan")}


def gt_depth_scale(a: Frame, b: Frame, lo: float = 0.6, hi: float = 1.4, n: int = 81) -> float:
    """The factor on the ground-truth translation under which a's depth, moved into b, best agrees
    with b's depth (truncated relative residual, rotation as given). 1 when ground truth and depth
    agree on the metre; a ground truth from structure from motion need not."""
    T = gt_T_b_a(a, b)
    grid = np.linspace(lo, hi, n)
    res = []
    for s in grid:
        Ts = T.copy()
        Ts[:3, 3] *= s
        z, zb = transfer_depth(a, b, Ts)
        good = zb > 0
        res.append(np.mean(np.minimum(np.abs(zb[good] - z[good]) / zb[good], 0.05)) if good.any() else np.inf)
    return float(grid[int(np.argmin(res))])


def pairs_of(frames: list[Frame], gaps: list[int]) -> list[tuple[Frame, Frame]]:
    """(ref, cur) for every ``cur`` index minus each gap, both directions."""
    out = []
    for g in gaps:
        for i in range(len(frames) - g):
            out += [(frames[i], frames[i + g]), (frames[i + g], frames[i])]
    return out


def run(name: str, frames: list[Frame], gaps: list[int], methods: list[str], args, enc, bbs) -> None:
    pairs = pairs_of(frames, gaps)
    if "gt-vs-depth" in methods:
        fit = [gt_depth_scale(r, c) for r, c in pairs[::2] if np.linalg.norm(gt_T_b_a(r, c)[:3, 3]) >= args.min_baseline]
        print(f"| {name} | gt-vs-depth | {len(fit)} | {np.median(fit):.3f} ({np.quantile(fit, 0.25):.3f}-"
              f"{np.quantile(fit, 0.75):.3f}) | - | - | - |", flush=True)
    for method in [m for m in methods if m != "gt-vs-depth"]:
        if method in ("keypoint_depths", "nearest"):
            res = [(pnp_pose(enc, r, c, method), gt_T_b_a(r, c)) for r, c in pairs]
        else:
            res = [(backbone_pose(bbs[method], r, c), gt_T_b_a(r, c)) for r, c in pairs]
        s = stats(res, args.min_baseline)
        print(f"| {name} | {method} | {s['n']}/{s['of']} | {s['ratio']:.3f} ({s['ratio_q25']:.3f}-{s['ratio_q75']:.3f}) "
              f"| {s['along']:.3f} | {s['err_mm']:.1f} | {s['rot_deg']:.2f} |", flush=True)


def run_step_lengths(run_dir: Path, min_true_m: float) -> tuple[list[float], list[float], int]:
    """Predicted and true step lengths of every robot of every encounter of one run folder
    (steps whose true length is below ``min_true_m`` left out) and the steps held."""
    import json

    import pandas as pd

    from cerpe.geometry import se3_from_tq_xyzw, se3_inverse
    from cerpe.pipeline.setting import load_manifest_setting

    setting = load_manifest_setting(Path(json.loads((run_dir / "run.json").read_text())["manifest"]))
    pred, true, held = [], [], 0
    for enc in setting.encounters:
        f = run_dir / enc.name / "robots.csv"
        if not f.is_file():
            continue
        df = pd.read_csv(f)
        for r in enc.robots:
            d = df[df.robot == r.robot_id].sort_values("step")
            held += int(d.degradations.astype(str).str.count("ego:step-held").sum())
            X = [se3_from_tq_xyzw(row[["odom_tx", "odom_ty", "odom_tz"]].to_numpy(float),
                                  row[["odom_qx", "odom_qy", "odom_qz", "odom_qw"]].to_numpy(float)) for _, row in d.iterrows()]
            G = r.T_world_cam[d.step.to_numpy()]
            for k in range(1, len(X)):
                if not (np.all(np.isfinite(G[k - 1])) and np.all(np.isfinite(G[k]))):
                    continue
                tg = float(np.linalg.norm((se3_inverse(G[k - 1]) @ G[k])[:3, 3]))
                if tg >= min_true_m:
                    pred.append(float(np.linalg.norm((se3_inverse(X[k - 1]) @ X[k])[:3, 3])))
                    true.append(tg)
    return pred, true, held


def runs_report(root: Path, method: str, min_true_m: float) -> None:
    """One line per set of ``root/runs``: the step-length figures of ``method``'s odometry."""
    import json

    from cerpe.scale import step_ratios

    print("| set | steps | median pred/true | p10 | p90 | outside [0.5, 2] | held |")
    print("|---|---|---|---|---|---|---|")
    for sd in sorted((root / "runs").iterdir()):
        rd = sd / method
        if not (rd / "run.json").is_file():
            continue
        if not json.loads((rd / "run.json").read_text()).get("metric_scale", True):
            print(f"| {sd.name} | no metric depth: up to scale | | | | | |")
            continue
        pred, true, held = run_step_lengths(rd, min_true_m)
        s = step_ratios(np.array(pred), np.array(true))
        print(f"| {sd.name} | {s['n']} | {s['median']:.3f} | {s['p10']:.3f} | {s['p90']:.3f} | {s['outside']} | {held} |",
              flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--min-baseline", type=float, default=0.02, help="pairs with a shorter true baseline are left out")
    ap.add_argument("--synth", nargs="*", default=[], help="synthetic manifest(s) as an exact-depth control")
    ap.add_argument("--methods", nargs="+",
                    default=["gt-vs-depth", "keypoint_depths", "nearest", "backbone", "backbone-nodense"])
    ap.add_argument("--data", nargs="+", default=["fr1", "sun3d"], help="real sets to run (fr1, sun3d)")
    ap.add_argument("--runs", type=Path, default=None,
                    help="a `cerpe dev --out` folder: measure its CERPE runs' odometry step lengths instead")
    ap.add_argument("--method", default="cerpe", help="with --runs: the method whose odometry is measured")
    ap.add_argument("--min-step", type=float, default=0.005,
                    help="with --runs: steps whose true length is shorter (m) are left out")
    args = ap.parse_args(argv)
    if args.runs is not None:
        runs_report(args.runs, args.method, args.min_step)
        return 0
    enc = XFeatEncoder()
    bbs = {"backbone": OfflineGeometryBackbone(encoder=enc),
           "backbone-nodense": OfflineGeometryBackbone(OfflineConfig(dense={"refine": False}), encoder=enc)}
    print("| data | method | pairs placed | median |t|/|t_gt| (IQR) | median along | median t err mm | median rot err deg |")
    print("|---|---|---|---|---|---|---|")
    if "fr1" in args.data and (DATA / "tum-fr1-xyz-10").is_dir():
        for label, kw in [("fr1 as stored", {}), ("fr1 undistorted", {"undistort": True}),
                          ("fr1 depth x1.035", {"depth_scale": 1.035}),
                          ("fr1 undistorted + x1.035", {"undistort": True, "depth_scale": 1.035})]:
            run(label, fr1_frames(**kw), [2, 3, 4, 6, 9], args.methods, args, enc, bbs)
    if "sun3d" in args.data and (DATA / "sun3d-two-fragments").is_dir():
        k570 = CameraIntrinsics(570.3, 570.3, 320.0, 240.0, 640, 480)  # SUN3D's own calibration
        for frag in ("fragment-1", "fragment-2"):
            frames = sun3d_fragment(frag)
            run(f"sun3d {frag}", frames, [5, 10, 20, 30], args.methods, args, enc, bbs)
            run(f"sun3d {frag} fx 570.3", [dataclasses.replace(f, K=k570) for f in frames], [5, 10, 20, 30],
                args.methods, args, enc, bbs)
    for m in args.synth:
        from cerpe.datasets import load_setting

        enc0 = load_setting(m).encounters[0]
        r = enc0.robots[0]
        frames = [Frame(f"{r.robot_id}:{t}", r.image(t), r.intrinsics, r.T_world_cam[t], r.depth_m(t))
                  for t in range(min(len(r), 30))]
        for label, dist in [("", None), (", fr1 lens not undone", DIST_FR1),
                            (", barrel k1=-0.2 not undone", np.array([-0.2, 0.0, 0.0, 0.0, 0.0]))]:
            fs = frames if dist is None else [distort_frame(f, dist) for f in frames]
            run(f"{Path(m).parent.name} {r.robot_id}{label}", fs, [2, 4], args.methods, args, enc, bbs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
