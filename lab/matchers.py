"""Cross-robot registration on development pairs: which matcher places the collaborator image.

For every case of every set (``lab/sets.py``: real pairs from ``../shared/data``
and synthetic suites rendered with seeds other than 0) and every matcher:

* matches between the ego robot's current frame and the collaborator image;
* verified inliers: the collaborator placed by P3P RANSAC (poselib, ``--pnp-px``) on the
  ego frame's metric depth at its keypoints (``keypoint_depths``, as the offline backbone
  samples it), or by the essential matrix (poselib 5-point, ``--epipolar-px``) where the
  ego frame has no depth; placed = at least ``--min-inliers`` inliers (and, for the
  essential matrix, an inlier ratio of ``--min-ratio``): the offline backbone's thresholds;
* errors of the recovered ``T_collab_ego`` against ground truth: rotation (deg),
  translation direction (deg), translation (m, metric sets only); a placed pair is
  *correct* when its rotation error is below 5 deg and its translation is within 0.25 m
  (metric) or 15 deg in direction (essential matrix; not judged below 5 cm of baseline);
* cost: feature extraction per image and matching per pair (ms, this CPU).

Then the memory study: the collaborator registered against each of the ego robot's
views (current frame first, then earlier frames standing in for memory keyframes) and
placed through the view with most verified inliers, against the current frame alone.

Matchers: ``xfeat-mnn`` (today's offline backbone: XFeat mutual nearest neighbours,
cosine > 0.82, ratio 0.95), ``xfeat-lg`` (LighterGlue over the same XFeat features, the
best 1024 keypoints), ``xfeat-lg-2k`` (all 2048), ``aliked-lg`` (ALIKED n16 1024 keypoints
at 640 px + LightGlue), ``aliked-lg-512`` (the same at 512 px, the baseline's setting).
``--reuse rows.json`` prints the tables again from saved rows (e.g. at other inlier thresholds).

    python -m lab.matchers --sets tum-fr3-office sun3d tum-fr1-xyz \\
        --synth build/dev-synth/indoor-s7/manifest.yaml build/dev-synth/cad-s7/manifest.yaml
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass
from functools import partial
from pathlib import Path
from typing import Any, Callable

import numpy as np

from cerpe.backbones.lightglue import AlikedExtractor, LightGlueMatcher, xfeat_inputs
from cerpe.backbones.offline import keypoint_depths, match_mnn
from cerpe.backbones.xfeat import XFeatEncoder

from .sets import Case, Frame, gt_T_b_a, load_sets

MATCHERS = ["xfeat-mnn", "xfeat-lg", "xfeat-lg-2k", "aliked-lg", "aliked-lg-512"]


@dataclass
class Matcher:
    name: str
    family: str  # matchers of one family share features
    features: Callable[[np.ndarray], dict]
    match: Callable[[dict, dict], np.ndarray]


def _lightglue(**kw) -> Callable[[dict, dict], np.ndarray]:
    lg = LightGlueMatcher(**kw)
    return lambda a, b: lg({"image0": a, "image1": b})["matches"]


def build_matchers(names: list[str]) -> list[Matcher]:
    out: list[Matcher] = []
    enc = None
    for n in names:
        if n.startswith("xfeat"):
            enc = enc or XFeatEncoder()
            feats = partial(_xfeat_features, enc)
            if n == "xfeat-mnn":
                out.append(Matcher(n, "xfeat", feats, lambda a, b: match_mnn(a["descriptors"], b["descriptors"], 0.82, 0.95)))
            elif n in ("xfeat-lg", "xfeat-lg-2k"):
                out.append(Matcher(n, "xfeat", feats, _lightglue(features="xfeat",
                                                                 max_keypoints=None if n.endswith("2k") else 1024)))
            else:
                raise SystemExit(f"unknown matcher {n!r}; known: {MATCHERS}")
        elif n in ("aliked-lg", "aliked-lg-512"):
            ex = AlikedExtractor(max_keypoints=1024, max_side_px=512 if n.endswith("512") else 640)
            out.append(Matcher(n, n, ex, _lightglue(features="aliked")))
        else:
            raise SystemExit(f"unknown matcher {n!r}; known: {MATCHERS}")
    return out


def _xfeat_features(enc: XFeatEncoder, image: np.ndarray) -> dict:
    return xfeat_inputs(enc.encode_image(image))


# ---------------------------------------------------------------------------- verification
def _cam(f: Frame) -> dict:
    K = f.K
    return {"model": "PINHOLE", "width": int(K.width), "height": int(K.height),
            "params": [float(K.fx), float(K.fy), float(K.cx), float(K.cy)]}


def _T(pose: Any) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = pose.R, pose.t
    return T


def verify(uv_ref: np.ndarray, uv_q: np.ndarray, ref: Frame, q: Frame, args: argparse.Namespace,
           depth_m: np.ndarray | None = None) -> tuple[np.ndarray | None, int, bool]:
    """``(T_q_ref or None, verified inliers, metric)`` from matched pixels (see module doc)."""
    import poselib

    ransac = {"min_iterations": 100, "max_iterations": 4000}
    D = ref.depth_m if depth_m is None else depth_m
    if D is not None:
        z = keypoint_depths(uv_ref, D, ref.image.shape[:2], 0.2)
        ok = z > 0
        if ok.sum() < args.min_inliers:
            return None, int(ok.sum()), True
        K = ref.K.K
        X = np.column_stack([(uv_ref[ok, 0] - K[0, 2]) / K[0, 0], (uv_ref[ok, 1] - K[1, 2]) / K[1, 1],
                             np.ones(ok.sum())]) * z[ok, None]
        pose, info = poselib.estimate_absolute_pose(uv_q[ok].astype(np.float64), X, _cam(q),
                                                    {**ransac, "max_reproj_error": args.pnp_px}, {})
        n = int(np.sum(info["inliers"]))
        return (_T(pose) if n >= args.min_inliers else None), n, True
    if len(uv_ref) < max(args.min_inliers, 5):
        return None, 0, False
    pose, info = poselib.estimate_relative_pose(uv_ref.astype(np.float64), uv_q.astype(np.float64), _cam(ref),
                                                _cam(q), {**ransac, "max_epipolar_error": args.epipolar_px}, {})
    inl = np.asarray(info["inliers"], bool)
    n = int(inl.sum())
    T = _T(pose)
    ok = n >= args.min_inliers and inl.mean() >= args.min_ratio and np.linalg.norm(T[:3, 3]) > 1e-9
    if ok:
        T[:3, 3] /= np.linalg.norm(T[:3, 3])
    return (T if ok else None), n, False


def errors(T: np.ndarray, T_gt: np.ndarray, metric: bool) -> dict[str, float]:
    R = T[:3, :3].T @ T_gt[:3, :3]
    rot = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
    t, tg = T[:3, 3], T_gt[:3, 3]
    cosd = t @ tg / max(np.linalg.norm(t) * np.linalg.norm(tg), 1e-12)
    out = {"rot_deg": rot, "dir_deg": float(np.degrees(np.arccos(np.clip(cosd, -1, 1)))),
           "t_err_m": float(np.linalg.norm(t - tg)) if metric else float("nan"),
           "len_ratio": float(np.linalg.norm(t) / max(np.linalg.norm(tg), 1e-12)) if metric else float("nan")}
    base = np.linalg.norm(tg)
    out["correct"] = bool(rot < 5.0 and ((out["t_err_m"] < 0.25) if metric else (base < 0.05 or out["dir_deg"] < 15.0)))
    return out


# ---------------------------------------------------------------------------- running
@dataclass
class Row:
    set: str
    matcher: str
    pair: str
    view: int  # index in Case.ego the collaborator was registered against
    overlap: float
    n_matches: int
    n_inliers: int
    placed: bool
    metric: bool
    rot_deg: float = float("nan")
    dir_deg: float = float("nan")
    t_err_m: float = float("nan")
    len_ratio: float = float("nan")
    correct: bool = False
    match_ms: float = float("nan")
    match_cpu_ms: float = float("nan")  # process CPU time: less sensitive to other jobs on the machine
    gt_angle_deg: float = float("nan")
    gt_baseline_m: float = float("nan")
    case: int = 0  # index of the case in its set (groups a collaborator's rows over ego views)


class FeatureCache:
    """Features per (family, frame key), with the seconds their extraction took."""

    def __init__(self) -> None:
        self.feats: dict[tuple, tuple[dict, float, float]] = {}

    def get(self, m: Matcher, f: Frame, role: str) -> tuple[dict, float, float]:
        """``(features, wall seconds, process CPU seconds)``."""
        key = (m.family, role, f.key)
        if key not in self.feats:
            t0, c0 = time.perf_counter(), time.process_time()
            out = m.features(f.image)
            self.feats[key] = (out, time.perf_counter() - t0, time.process_time() - c0)
        return self.feats[key]


def register(m: Matcher, cache: FeatureCache, case: Case, view: int, args: argparse.Namespace) -> Row:
    ref, q = case.ego[view], case.collab
    fr = cache.get(m, ref, "ego")[0]
    fq = cache.get(m, q, "collab")[0]
    t0, c0 = time.perf_counter(), time.process_time()
    mm = m.match(fr, fq)
    ms, cpu = 1e3 * (time.perf_counter() - t0), 1e3 * (time.process_time() - c0)
    uv_r, uv_q = fr["keypoints"][mm[:, 0]], fq["keypoints"][mm[:, 1]]
    T, n, metric = verify(uv_r, uv_q, ref, q, args)
    T_gt = gt_T_b_a(ref, q)
    row = Row(case.set, m.name, f"{ref.key}>{q.key}", view, case.overlap, len(mm), n, T is not None, metric,
              match_ms=ms, match_cpu_ms=cpu, gt_baseline_m=float(np.linalg.norm(T_gt[:3, 3])),
              gt_angle_deg=float(np.degrees(np.arccos(np.clip((np.trace(T_gt[:3, :3]) - 1) / 2, -1, 1)))))
    if T is not None:
        for k, v in errors(T, T_gt, metric).items():
            setattr(row, k, v)
    return row


def _med(x: list[float]) -> float:
    x = [v for v in x if np.isfinite(v)]
    return float(np.median(x)) if x else float("nan")


def _fmt(v: float, spec: str) -> str:
    return "-" if not np.isfinite(v) else format(v, spec)


def _placed(r: Row, min_inliers: int) -> bool:
    return r.placed and r.n_inliers >= min_inliers


def _pcw(rs: list[Row], k: int) -> str:
    """``placed (correct/wrong)`` at ``k`` verified inliers."""
    pl = [r for r in rs if _placed(r, k)]
    return f"{len(pl)} ({sum(r.correct for r in pl)}/{sum(not r.correct for r in pl)})"


def print_table(name: str, rows: list[Row], feat_ms: dict[str, tuple[float, float]], thresholds: list[int],
                out=sys.stdout) -> None:
    """Per matcher: placements at each inlier threshold, errors over pairs placed at the first, and cost
    (wall / process-CPU ms; CPU time counts both threads and is less disturbed by other jobs)."""
    has_ov = any(np.isfinite(r.overlap) for r in rows)
    k0 = thresholds[0]
    print(f"\n### {name}: collaborator vs ego current frame ({len({r.pair for r in rows})} pairs; "
          f"placed (correct/wrong) at >= N verified inliers)", file=out)
    hdr = (["matcher"] + [f"placed >={k}" for k in thresholds]
           + (["placed ov>=0.2", "placed ov<0.05"] if has_ov else [])
           + ["med matches", "med inliers", "med rot deg", "med dir deg", "med t err m", "med |t|/|t_gt|",
              "feat ms/img wall/cpu", "match ms/pair wall/cpu"])
    print("| " + " | ".join(hdr) + " |", file=out)
    print("|" + "---|" * len(hdr), file=out)
    for mname in dict.fromkeys(r.matcher for r in rows):
        rs = [r for r in rows if r.matcher == mname]
        pl = [r for r in rs if _placed(r, k0)]
        cells = [mname] + [_pcw(rs, k) for k in thresholds]
        if has_ov:
            pos = [r for r in rs if r.overlap >= 0.2]
            neg = [r for r in rs if r.overlap < 0.05]
            cells += [f"{sum(_placed(r, k0) for r in pos)}/{len(pos)}", f"{sum(_placed(r, k0) for r in neg)}/{len(neg)}"]
        cells += [_fmt(_med([r.n_matches for r in rs]), ".0f"), _fmt(_med([r.n_inliers for r in rs]), ".0f"),
                  _fmt(_med([r.rot_deg for r in pl]), ".2f"), _fmt(_med([r.dir_deg for r in pl]), ".1f"),
                  _fmt(_med([r.t_err_m for r in pl]), ".3f"), _fmt(_med([r.len_ratio for r in pl]), ".3f"),
                  "/".join(_fmt(v, ".0f") for v in feat_ms.get(mname, (float("nan"),) * 2)),
                  _fmt(_med([r.match_ms for r in rs]), ".0f") + "/" + _fmt(_med([r.match_cpu_ms for r in rs]), ".0f")]
        print("| " + " | ".join(cells) + " |", file=out)


def memory_table(name: str, rows: list[Row], thresholds: list[int], out=sys.stdout) -> None:
    """Current frame alone against the ego view with most verified inliers (ties: the current frame)."""
    print(f"\n### {name}: current frame alone vs best of current + memory views "
          f"(placed (correct/wrong) at >= N inliers)", file=out)
    hdr = ["matcher", "pairs"] + [f"{w} >={k}" for k in thresholds for w in ("current", "memory")] + [
        "memory view chosen", "match ms/collab (all views)"]
    print("| " + " | ".join(hdr) + " |", file=out)
    print("|" + "---|" * len(hdr), file=out)
    for mname in dict.fromkeys(r.matcher for r in rows):
        by_pair: dict[tuple, list[Row]] = {}
        for r in rows:
            if r.matcher == mname:
                by_pair.setdefault((r.set, r.pair.split(">")[1], r.case), []).append(r)
        cur = [min(rs, key=lambda r: r.view) for rs in by_pair.values()]
        cells = [mname, str(len(by_pair))]
        for k in thresholds:
            best = [max(rs, key=lambda r: (_placed(r, k), r.n_inliers, -r.view)) for rs in by_pair.values()]
            cells += [_pcw(cur, k), _pcw(best, k)]
        best0 = [max(rs, key=lambda r: (_placed(r, thresholds[0]), r.n_inliers, -r.view)) for rs in by_pair.values()]
        cells += [str(sum(b.view > 0 and _placed(b, thresholds[0]) for b in best0)),
                  _fmt(_med([sum(r.match_ms for r in rs) for rs in by_pair.values()]), ".0f")]
        print("| " + " | ".join(cells) + " |", file=out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", nargs="*", default=["tum-fr3-office", "sun3d", "tum-fr1-xyz"])
    ap.add_argument("--synth", nargs="*", default=[], help="manifest.yaml of synthetic suites (seed != 0)")
    ap.add_argument("--matchers", nargs="+", default=MATCHERS)
    ap.add_argument("--min-inliers", type=int, nargs="+", default=[25, 50],
                    help="verified-inlier thresholds to report (the first also sets the RANSAC acceptance)")
    ap.add_argument("--min-ratio", type=float, default=0.2)
    ap.add_argument("--pnp-px", type=float, default=3.0)
    ap.add_argument("--epipolar-px", type=float, default=1.0)
    ap.add_argument("--no-memory", action="store_true", help="skip the memory study")
    ap.add_argument("--max-cases", type=int, default=0, help="first N cases per set (0: all)")
    ap.add_argument("--json", help="write every row here")
    ap.add_argument("--reuse", help="print the tables from rows a previous --json wrote (no matching)")
    args = ap.parse_args(argv)
    thresholds = sorted(args.min_inliers)
    args.min_inliers = thresholds[0]
    if args.reuse:
        rows = [Row(**{k: v for k, v in d.items() if k in Row.__dataclass_fields__})
                for d in json.loads(Path(args.reuse).read_text())]
        for sname in dict.fromkeys(r.set for r in rows):
            rs = [r for r in rows if r.set == sname and r.matcher in args.matchers]
            print_table(sname, [r for r in rs if r.view == 0], {}, thresholds)
            if any(r.view > 0 for r in rs):
                memory_table(sname, rs, thresholds)
        return 0
    sets = load_sets(args.sets, [Path(p) for p in args.synth])
    matchers = build_matchers(args.matchers)
    all_rows: list[Row] = []
    for sname, cases in sets.items():
        if args.max_cases:
            cases = cases[:args.max_cases]
        cache = FeatureCache()
        rows: list[Row] = []
        for m in matchers:
            for ci, case in enumerate(cases):
                for v in range(1 if args.no_memory else len(case.ego)):
                    r = register(m, cache, case, v, args)
                    r.case = ci
                    rows.append(r)
        feat_ms = {m.name: (1e3 * _med([w for (fam, _, _), (_, w, _) in cache.feats.items() if fam == m.family]),
                            1e3 * _med([c for (fam, _, _), (_, _, c) in cache.feats.items() if fam == m.family]))
                   for m in matchers}
        print_table(sname, [r for r in rows if r.view == 0], feat_ms, thresholds)
        if not args.no_memory:
            memory_table(sname, rows, thresholds)
        sys.stdout.flush()
        all_rows += rows
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps([asdict(r) for r in all_rows], indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
