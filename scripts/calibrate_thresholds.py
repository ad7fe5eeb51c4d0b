#!/usr/bin/env python
"""Calibrate the offline descriptor's thresholds tau (gate), tau_m and tau_k (memory) on development data.

Data (never the paper-default suite, seed 0, which is refused):

* synthetic development suites (--synth-seeds, default 2001): both worlds rendered as
  `cerpe dev` renders them (cached in build/dev/synth/);
* the real development sets with ground-truth co-visibility (--real, default every enabled
  datasets_manifest/dev-*.yaml whose robots have depth and poses: SUN3D two fragments,
  TUM fr1/xyz; fr3/office has no depth and is skipped with a line saying so).

Per set, the gate's samples are pairs of views of two robots of one encounter at any two
steps (t, u on --stride), labelled with the co-visibility label of the unordered pair
(overlap >= 0.2 both ways positive, < 0.05 both ways negative, the rest left out),
the overlap computed from depth and ground-truth poses; the real sets also get
cross-scene negatives (views of the other real sets: another place), without which a
recording whose robots always see each other has no negatives; their AUC and precision
are upper estimates. Same-step figures (what a run's gate sees) are printed beside them.

Rule for tau: the largest tau at which the recall is >= --min-recall (0.8) on every set
(a closed gate loses the anchor; a needless request costs bytes and is checked by the
registration), rounded down to 4 decimals. tau_m and tau_k: the --q-m (0.10) and --q-k
(0.01) quantiles of the similarity of consecutive frames of one robot, each set weighted
equally, over the sets chosen by --memory-from (default: synth, the 10 Hz robot streams;
the real recordings are 30 Hz, where consecutive frames barely differ; their quantiles
are printed).

Prints per set ROC AUC, precision, recall at the old and the new tau, the best recall at
precision >= 0.8, and whether issue 18's targets (AUC >= 0.90, recall >= 0.8 at precision
>= 0.8) are met; writes cerpe/data/xfeat_salad_thresholds.json (atomically) with the
thresholds, the rule, the figures and the provenance (data, seeds, command, revision).

    python scripts/calibrate_thresholds.py                      # synthetic seed 2001 + the real dev sets
    python scripts/calibrate_thresholds.py --synth-seeds 2001 2002 --dry-run
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "cerpe" / "data" / "xfeat_salad_thresholds.json"


def _args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--synth-seeds", type=int, nargs="*", default=[2001],
                    help="synthetic development seeds (default: 2001; 0 is the paper-default suite and refused)")
    ap.add_argument("--synth-preset", default="dev", choices=("dev", "fixture"),
                    help="synthetic suite sizes (as `cerpe dev --synth`)")
    ap.add_argument("--real", nargs="*", default=None,
                    help="real development manifests (default: the enabled datasets_manifest/dev-*.yaml)")
    ap.add_argument("--dev-out", type=Path, default=ROOT / "build" / "dev",
                    help="where the synthetic suites are rendered (the `cerpe dev` cache)")
    ap.add_argument("--stride-synth", type=int, default=2, help="step stride of synthetic any-step pairs")
    ap.add_argument("--stride-real", type=int, default=1, help="step stride of real any-step pairs")
    ap.add_argument("--no-cross-scene", action="store_true", help="no cross-scene negatives for the real sets")
    ap.add_argument("--min-recall", type=float, default=0.8)
    ap.add_argument("--q-m", type=float, default=0.10)
    ap.add_argument("--q-k", type=float, default=0.01)
    ap.add_argument("--memory-from", choices=("synth", "all"), default="synth",
                    help="the sets tau_m and tau_k are taken from (default: synth)")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--samples", type=Path, default=None,
                    help="also write every labelled pair (set, sample, scores, overlaps, label) to this CSV")
    ap.add_argument("--dry-run", action="store_true", help="print, do not write")
    return ap.parse_args(argv)


def _sets(a: argparse.Namespace) -> list[tuple[str, str, object, Path]]:
    """``(name, kind, setting, manifest)`` of every calibration set (kind: synthetic | real)."""
    from cerpe.datasets import find_manifests, load_setting
    from cerpe.pipeline.dev import PAPER_SEED, synthetic_set
    from cerpe.synth import SUITES

    out = []
    for seed in a.synth_seeds:
        if seed == PAPER_SEED:
            raise SystemExit("calibrate: seed 0 is the paper-default suite (test data); use development seeds")
        for setting in SUITES["paper-default"]:
            s = synthetic_set(setting, seed, a.synth_preset, a.dev_out)
            out.append((s.name, "synthetic", load_setting(s.manifest), Path(s.manifest)))
    reals = a.real if a.real is not None else [
        str(m.path) for m in find_manifests(ROOT / "datasets_manifest") if m.name.startswith("dev-") and m.enabled]
    for path in reals:
        setting = load_setting(path)
        if any(e.overlap is None for e in setting.encounters):
            print(f"calibrate: {setting.name}: no ground-truth co-visibility (no depth); skipped for the gate",
                  file=sys.stderr)
            continue
        out.append((setting.name, "real", setting, Path(path)))
    return out


def _fmt(v: float, nd: int = 3) -> str:
    return "--" if v is None or not np.isfinite(v) else f"{v:.{nd}f}"


def _verdict(met: bool, f: dict) -> str:
    """A target's verdict; ``n/a`` where a class is missing (a sample without negatives ranks nothing)."""
    return "n/a (one class)" if not (f["n_positive"] and f["n_negative"]) else ("met" if met else "NOT met")


def main(argv: list[str] | None = None) -> int:
    a = _args(argv)
    import pandas as pd

    from cerpe import knobs
    from cerpe.atomicio import atomic_write_text
    from cerpe.backbones.descriptor import XFeatSaladDescriptor
    from cerpe.pipeline.calibrate import (consecutive_similarity, cross_scene_negatives, describe_encounter,
                                          largest_tau_with_recall, pair_samples, set_figures)
    from cerpe.pipeline.provenance import file_digest, git_revision

    t0 = time.perf_counter()
    old = json.loads(a.out.read_text())["thresholds"] if a.out.is_file() else {"tau": np.nan, "tau_m": np.nan,
                                                                                 "tau_k": np.nan}
    desc = XFeatSaladDescriptor(thresholds={"tau": 0.0, "tau_m": 0.0, "tau_k": 0.0})
    sets = _sets(a)
    if not sets:
        print("calibrate: no calibration data", file=sys.stderr)
        return 2
    D, any_step, same_step, consec = {}, {}, {}, {}
    for name, kind, setting, _ in sets:
        stride = a.stride_synth if kind == "synthetic" else a.stride_real
        D[name], any_step[name], same_step[name], consec[name] = [], [], [], []
        for enc in setting.encounters:
            Denc = describe_encounter(desc, enc)
            D[name].append(Denc)
            any_step[name].append(pair_samples(enc, Denc, stride=stride, any_step=True))
            same_step[name].append(pair_samples(enc, Denc, any_step=False))
            consec[name].append(consecutive_similarity(Denc))
        any_step[name] = pd.concat(any_step[name], ignore_index=True)
        same_step[name] = pd.concat(same_step[name], ignore_index=True)
        consec[name] = np.concatenate(consec[name])
    kinds = {name: kind for name, kind, _, _ in sets}

    def samples(name: str, table: dict) -> tuple[np.ndarray, np.ndarray]:
        df = table[name][table[name]["label"].notna()]
        s, y = df["score"].to_numpy(float), df["label"].to_numpy(float) > 0.5
        if kinds[name] == "real" and not a.no_cross_scene and table is any_step:
            others = [d for n, ds in D.items() if n != name and kinds[n] == "real" for d in ds]
            neg = np.concatenate([cross_scene_negatives(d, others, a.stride_real) for d in D[name]])
            s, y = np.r_[s, neg], np.r_[y, np.zeros(neg.size, bool)]
        return s, y

    cal = {name: samples(name, any_step) for name in D}
    tau = largest_tau_with_recall(cal, a.min_recall)
    mem_sets = [n for n in D if a.memory_from == "all" or kinds[n] == "synthetic"] or list(D)
    weights = np.concatenate([np.full(consec[n].size, 1.0 / consec[n].size) for n in mem_sets])
    values = np.concatenate([consec[n] for n in mem_sets])

    def wquantile(q: float) -> float:
        order = np.argsort(values)
        cw = np.cumsum(weights[order]) / weights.sum()
        return float(values[order][np.searchsorted(cw, q)])

    tau_m = round(wquantile(a.q_m), 4)
    tau_k = round(min(wquantile(a.q_k), tau_m), 4)
    figures = {}
    for name in D:
        entry = {"kind": kinds[name]}
        for label, table in (("any_step", any_step), ("same_step", same_step)):
            s, y = cal[name] if table is any_step else samples(name, same_step)
            entry[label] = {"before": set_figures(s, y, old["tau"]), "after": set_figures(s, y, tau),
                            "n_left_out": int(table[name]["label"].isna().sum())}
        entry["consecutive_q"] = {"q_m": float(np.quantile(consec[name], a.q_m)),
                                  "q_k": float(np.quantile(consec[name], a.q_k)), "n": int(consec[name].size)}
        figures[name] = entry

    head = (f"{'set':<34}{'sample':<10}{'pos':>6}{'neg':>7}{'AUC':>7}  {'P/R before':>13}  {'P/R after':>13}"
            f"{'R@P80':>7}  targets")
    print(f"tau {old['tau']:.4f} -> {tau:.4f} (largest with recall >= {a.min_recall} on every set); "
          f"tau_m {old['tau_m']:.4f} -> {tau_m:.4f}, tau_k {old['tau_k']:.4f} -> {tau_k:.4f} "
          f"(consecutive-frame quantiles of {', '.join(mem_sets)})")
    print(head)
    for name, e in figures.items():
        for label in ("any_step", "same_step"):
            b, f = e[label]["before"], e[label]["after"]
            print(f"{name:<34}{label:<10}{f['n_positive']:>6}{f['n_negative']:>7}{_fmt(f['roc_auc']):>7}  "
                  f"{_fmt(b['precision'], 2):>6}/{_fmt(b['recall'], 2):<6}  {_fmt(f['precision'], 2):>6}/"
                  f"{_fmt(f['recall'], 2):<6}{_fmt(f['recall_at_p80'], 2):>7}  "
                  f"AUC {_verdict(f['auc_target_met'], f)}, R@P80 {_verdict(f['pr_target_met'], f)}")
        q = e["consecutive_q"]
        print(f"{'':<34}consecutive frames: q{a.q_m:g} {q['q_m']:.4f}, q{a.q_k:g} {q['q_k']:.4f} (n={q['n']})")
    result = {
        "thresholds": {"tau": tau, "tau_m": tau_m, "tau_k": tau_k},
        "previous": old,
        "rule": {"tau": f"largest tau (rounded down to 4 decimals) with recall >= {a.min_recall} on every set, over "
                        "pairs of views of two robots at any two steps labelled with the co-visibility label "
                        "(overlap >= 0.2 both ways positive, < 0.05 both ways negative, the rest left out)",
                 "tau_m": f"quantile {a.q_m} of consecutive-frame similarity, sets weighted equally: {mem_sets}",
                 "tau_k": f"quantile {a.q_k} of the same (at most tau_m)"},
        "figures": figures,
        "provenance": {
            "synthetic": {"seeds": a.synth_seeds, "preset": a.synth_preset, "stride": a.stride_synth,
                          "sets": [n for n in D if kinds[n] == "synthetic"]},
            "real": {n: {"manifest": str(m.resolve().relative_to(ROOT)) if m.resolve().is_relative_to(ROOT)
                         else str(m), "manifest_sha": file_digest(m), "stride": a.stride_real,
                         "cross_scene_negatives": not a.no_cross_scene}
                     for n, k, _, m in sets if k == "real"},
            "command": " ".join(["python scripts/calibrate_thresholds.py", *(sys.argv[1:] if argv is None else argv)]),
            "git_revision": git_revision(), "date": time.strftime("%Y-%m-%d"),
            "never": "the paper-default suite (seed 0)"},
        "descriptor_dim": desc.dim,
        "descriptor_conf": knobs.as_dict(desc.conf),
    }
    if a.samples:
        rows = [t[n].assign(set=n, sample=lab) for lab, t in (("any_step", any_step), ("same_step", same_step))
                for n in D]
        atomic_write_text(a.samples, pd.concat(rows, ignore_index=True).to_csv(index=False, float_format="%.6g"))
        print(f"wrote {a.samples}")
    if not a.dry_run:
        atomic_write_text(a.out, json.dumps(result, indent=2, default=float) + "\n")
        print(f"wrote {a.out}")
    print(f"done in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
