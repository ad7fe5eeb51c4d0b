#!/usr/bin/env python
"""Calibrate the offline descriptor's thresholds tau (gate), tau_m and tau_k (memory).

On a synthetic evaluation suite with ground-truth overlap (Encounter.overlap [T,N,N]):

* tau: over all ordered cross-robot pairs (t, i, j), the score s = cos(d_i^t, d_j^t)
  (descriptors quantised as fp16, as on the wire) against the label
  "overlap ratio >= 0.2"; prints the ROC AUC and picks the tau that maximises F1
  (precision and recall at it printed too). The overlap ratio is directional (the
  fraction of i's pixels that j sees) and the cosine is not, so it also prints the
  best AUC any symmetric score could reach on these pairs (roc_auc_ceiling), the
  share of pairs whose two directions disagree, and the AUC on the pairs whose two
  directions agree (pipeline.evaluate.symmetric_bound).
* tau_m: the --q-m quantile (default 0.10) of the similarity of consecutive frames of
  one robot: a frame less similar to the last keyframe than 90 % of consecutive
  frames are to each other has moderately changed viewpoint.
* tau_k: the --q-k quantile (default 0.01) of the same: a change larger than almost
  any between consecutive frames is a large viewpoint change.

Writes cerpe/data/xfeat_salad_thresholds.json (atomically) with the thresholds and the
statistics; XFeatSaladDescriptor reads its defaults from it.

    python scripts/calibrate_thresholds.py --manifest build/synth/<suite>/manifest.yaml
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--manifest", nargs="+", help="suite manifest(s) with overlap ground truth")
    src.add_argument("--synth", nargs="+", metavar="SETTING:INDEX",
                     help="render encounter INDEX of the paper-default suite's SETTING in memory "
                          "(e.g. synthetic-cad:0 synthetic-indoor:1), same arguments as the suite")
    ap.add_argument("--seed", type=int, default=None,
                    help="render --synth encounters with this seed instead of the suite's (calibrate on "
                         "scenes the evaluation never sees, e.g. --seed 2001)")
    ap.add_argument("--overlap", type=float, default=0.2, help="overlap ratio that counts as overlapping")
    ap.add_argument("--q-m", type=float, default=0.10)
    ap.add_argument("--q-k", type=float, default=0.01)
    ap.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "cerpe" / "data" /
                                          "xfeat_salad_thresholds.json"))
    ap.add_argument("--dry-run", action="store_true", help="print, do not write")
    a = ap.parse_args(argv)

    from cerpe.backbones.descriptor import XFeatSaladDescriptor
    from cerpe.datasets import load_setting
    from cerpe.pipeline.evaluate import best_f1, roc_auc, symmetric_bound
    from cerpe.protocols import View

    desc = XFeatSaladDescriptor({"thresholds": {"tau": 0.0, "tau_m": 0.0, "tau_k": 0.0}})
    cross_s, cross_y, cross_rev, consec = [], [], [], []

    def _encounters():
        if a.manifest:
            for mpath in a.manifest:
                yield from load_setting(mpath).encounters
            return
        from cerpe.synth import SUITES, render_encounter

        for spec in a.synth:
            setting, index = spec.split(":")
            world, conf = SUITES["paper-default"][setting]
            conf = {k: v for k, v in conf.items() if k != "workers"}
            seed = conf.get("seed", 0) if a.seed is None else a.seed
            yield render_encounter(world, seed=seed, index=int(index), conf=conf, progress=True)

    for enc in _encounters():
        if True:
            if enc.overlap is None:
                print(f"calibrate: {enc.name} has no overlap ground truth; skipped", file=sys.stderr)
                continue
            D = np.zeros((enc.n_steps, len(enc.robots), desc.dim), np.float32)
            for i, r in enumerate(enc.robots):
                for t in tqdm(range(enc.n_steps), desc=f"{enc.name}/{r.robot_id}", unit="img", leave=False):
                    d = desc.describe(View((r.robot_id, t), r.image(t), r.intrinsics))
                    D[t, i] = d.astype(np.float16).astype(np.float32)  # the wire precision
                    D[t, i] /= np.linalg.norm(D[t, i])
                consec.extend(np.sum(D[1:, i] * D[:-1, i], axis=1).tolist())
            N = len(enc.robots)
            for t in range(enc.n_steps):
                for i in range(N):
                    for j in range(N):
                        if i != j and np.isfinite(enc.overlap[t, i, j]):
                            cross_s.append(float(D[t, i] @ D[t, j]))
                            cross_y.append(bool(enc.overlap[t, i, j] >= a.overlap))
                            cross_rev.append(bool(enc.overlap[t, j, i] >= a.overlap))
    s, y, c = np.asarray(cross_s), np.asarray(cross_y, bool), np.asarray(consec)
    if len(s) == 0 or y.all() or (~y).all():
        print("calibrate: need overlapping and non-overlapping cross-robot pairs", file=sys.stderr)
        return 2
    auc = roc_auc(s, y)
    f1 = best_f1(s, y)
    tau_m = float(np.quantile(c, a.q_m))
    tau_k = float(min(np.quantile(c, a.q_k), tau_m))
    result = {
        "thresholds": {"tau": round(f1["tau"], 4), "tau_m": round(tau_m, 4), "tau_k": round(tau_k, 4)},
        "gate": {"roc_auc": auc, **f1, **symmetric_bound(s, y, np.asarray(cross_rev, bool)),
                 "n_pairs": int(len(s)), "n_overlapping": int(y.sum()),
                 "overlap_threshold": a.overlap},
        "consecutive": {"n": int(len(c)), "q_m": a.q_m, "q_k": a.q_k, "median": float(np.median(c))},
        "sources": a.manifest or [f"paper-default {x} seed {a.seed}" for x in a.synth], "descriptor_dim": desc.dim, "descriptor_conf": {
            k: v for k, v in desc.conf.items() if k not in ("thresholds", "xfeat")},
    }
    print(json.dumps(result, indent=2))
    if not a.dry_run:
        dst = Path(a.out)
        tmp = dst.with_name(dst.name + ".tmp")
        tmp.write_text(json.dumps(result, indent=2) + "\n")
        os.replace(tmp, dst)
        print(f"wrote {dst}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
