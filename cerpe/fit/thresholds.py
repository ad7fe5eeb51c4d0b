"""Calibrate the offline descriptor's thresholds tau (gate), tau_m and tau_k (memory) on development data
(``cerpe fit thresholds``).

Data (never the paper-default suite, seed 0, which is refused):

* synthetic development suites (``--synth-seeds``, default 2001): both worlds rendered as
  ``cerpe dev`` renders them (cached in ``build/dev/synth/``);
* the real development sets with ground-truth co-visibility (``--real``, default every
  enabled ``datasets_manifest/dev-*.yaml`` whose robots have depth and poses: SUN3D two
  fragments, TUM fr1/xyz; fr3/office has no depth and is skipped with a line saying so).

Per set, the gate's samples are pairs of views of two robots of one encounter at any two
steps (t, u on a stride), labelled with the co-visibility label of the unordered pair
(overlap >= 0.2 both ways positive, < 0.05 both ways negative, the rest left out), the
overlap computed from depth and ground-truth poses (:mod:`cerpe.fit.calibrate`); the real
sets also get cross-scene negatives (views of the other real sets: another place), without
which a recording whose robots always see each other has no negatives; their AUC and
precision are upper estimates. Same-step figures (what a run's gate sees) are printed beside them.

Rule for tau: the largest tau at which the recall is >= ``--min-recall`` (0.8) on every set
(a closed gate loses the anchor; a needless request costs bytes and is checked by the
registration), rounded down to 4 decimals. tau_m and tau_k: the ``--q-m`` (0.10) and
``--q-k`` (0.01) quantiles of the similarity of consecutive frames of one robot, each set weighted
equally, over the sets chosen by ``--memory-from`` (default: synth, the 10 Hz robot streams;
the real recordings are 30 Hz, where consecutive frames barely differ; their quantiles are
printed).

Prints per set ROC AUC, precision, recall at the old and the new tau, the best recall at
precision >= 0.8, and whether the gate's targets (AUC >= 0.90, recall >= 0.8 at precision
>= 0.8) are met; writes ``cerpe/data/xfeat_salad_thresholds.json`` (atomically) with the
thresholds, the rule, the figures and the provenance (data, seeds, command, revision).
"""
from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .. import knobs
from . import DATA_DIR, FitError
from ..pipeline.dev import ROOT

DEFAULT_OUT = DATA_DIR / "xfeat_salad_thresholds.json"

default_conf: dict[str, Any] = {
    "synth_seeds": (2001,),  # synthetic development seeds (0, the paper-default suite, is refused)
    "synth_preset": "dev",  # synthetic suite sizes, as `cerpe dev --synth`: dev | fixture
    "stride_synth": 2,  # step stride of synthetic any-step pairs
    "stride_real": 1,  # step stride of real any-step pairs
    "cross_scene": True,  # cross-scene negatives for the real sets
    "min_recall": 0.8,
    "q_m": 0.10,
    "q_k": 0.01,
    "memory_from": "synth",  # the sets tau_m and tau_k are taken from: synth | all
    "dry_run": False,  # print, do not write
    "command": "",  # what made the file, recorded in its provenance
}


@dataclass(frozen=True)
class Paths:
    """The real development manifests (None: the enabled ``datasets_manifest/dev-*.yaml``), where the
    synthetic suites are rendered (the ``cerpe dev`` cache), the thresholds file, and optionally a CSV
    of every labelled pair."""

    real: tuple[Path, ...] | None = None
    dev_out: Path = ROOT / "build" / "dev"
    out: Path = DEFAULT_OUT
    samples: Path | None = None


def _sets(conf: dict, paths: Paths) -> list[tuple[str, str, object, Path]]:
    """``(name, kind, setting, manifest)`` of every calibration set (kind: synthetic | real)."""
    from ..datasets import find_manifests, load_setting
    from ..pipeline.dev import PAPER_SEED, synthetic_set
    from ..synth import SUITES

    out = []
    for seed in conf["synth_seeds"]:
        if seed == PAPER_SEED:
            raise FitError("seed 0 is the paper-default suite (test data); use development seeds")
        for setting in SUITES["paper-default"]:
            s = synthetic_set(setting, seed, conf["synth_preset"], paths.dev_out)
            out.append((s.name, "synthetic", load_setting(s.manifest), Path(s.manifest)))
    reals = paths.real if paths.real is not None else [
        str(m.path) for m in find_manifests(ROOT / "datasets_manifest") if m.name.startswith("dev-") and m.enabled]
    for path in reals:
        setting = load_setting(path)
        if any(e.overlap is None for e in setting.encounters):
            print(f"cerpe fit thresholds: {setting.name}: no ground-truth co-visibility (no depth); skipped for the "
                  f"gate", file=sys.stderr)
            continue
        out.append((setting.name, "real", setting, Path(path)))
    return out


def _fmt(v: float, nd: int = 3) -> str:
    return "--" if v is None or not np.isfinite(v) else f"{v:.{nd}f}"


def _verdict(met: bool, f: dict) -> str:
    """A target's verdict; ``n/a`` where a class is missing (a sample without negatives ranks nothing)."""
    return "n/a (one class)" if not (f["n_positive"] and f["n_negative"]) else ("met" if met else "NOT met")


def _print_figures(figures: dict, conf: dict) -> None:
    head = (f"{'set':<34}{'sample':<10}{'pos':>6}{'neg':>7}{'AUC':>7}  {'P/R before':>13}  {'P/R after':>13}"
            f"{'R@P80':>7}  targets")
    print(head)
    for name, e in figures.items():
        for label in ("any_step", "same_step"):
            b, f = e[label]["before"], e[label]["after"]
            print(f"{name:<34}{label:<10}{f['n_positive']:>6}{f['n_negative']:>7}{_fmt(f['roc_auc']):>7}  "
                  f"{_fmt(b['precision'], 2):>6}/{_fmt(b['recall'], 2):<6}  {_fmt(f['precision'], 2):>6}/"
                  f"{_fmt(f['recall'], 2):<6}{_fmt(f['recall_at_p80'], 2):>7}  "
                  f"AUC {_verdict(f['auc_target_met'], f)}, R@P80 {_verdict(f['pr_target_met'], f)}")
        q = e["consecutive_q"]
        print(f"{'':<34}consecutive frames: q{conf['q_m']:g} {q['q_m']:.4f}, q{conf['q_k']:g} {q['q_k']:.4f} "
              f"(n={q['n']})")


def main(conf: dict, paths: Paths) -> Path | None:
    """Calibrate, print the figures and write the thresholds file; returns it (None with ``dry_run``)."""
    conf = {**default_conf, **conf}
    if conf["memory_from"] not in ("synth", "all"):
        raise FitError(f"memory_from {conf['memory_from']!r}: synth or all")
    import pandas as pd

    from ..atomicio import atomic_write_text
    from ..backbones.descriptor import XFeatSaladDescriptor
    from ..runfolder.provenance import file_digest, git_revision
    from .calibrate import (consecutive_similarity, cross_scene_negatives, describe_encounter,
                            largest_tau_with_recall, pair_samples, set_figures)

    t0 = time.perf_counter()
    out = Path(paths.out)
    old = json.loads(out.read_text())["thresholds"] if out.is_file() else {"tau": np.nan, "tau_m": np.nan,
                                                                           "tau_k": np.nan}
    desc = XFeatSaladDescriptor(thresholds={"tau": 0.0, "tau_m": 0.0, "tau_k": 0.0})
    sets = _sets(conf, paths)
    if not sets:
        raise FitError("no calibration data (no synthetic seed, no real development set with depth)")
    D, any_step, same_step, consec = {}, {}, {}, {}
    for name, kind, setting, _ in sets:
        stride = conf["stride_synth"] if kind == "synthetic" else conf["stride_real"]
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
        if kinds[name] == "real" and conf["cross_scene"] and table is any_step:
            others = [d for n, ds in D.items() if n != name and kinds[n] == "real" for d in ds]
            neg = np.concatenate([cross_scene_negatives(d, others, conf["stride_real"]) for d in D[name]])
            s, y = np.r_[s, neg], np.r_[y, np.zeros(neg.size, bool)]
        return s, y

    cal = {name: samples(name, any_step) for name in D}
    try:
        tau = largest_tau_with_recall(cal, conf["min_recall"])
    except ValueError as exc:
        raise FitError(f"{exc}: no set has a co-visible pair to calibrate tau on") from None
    mem_sets = [n for n in D if conf["memory_from"] == "all" or kinds[n] == "synthetic"] or list(D)
    weights = np.concatenate([np.full(consec[n].size, 1.0 / consec[n].size) for n in mem_sets])
    values = np.concatenate([consec[n] for n in mem_sets])

    def wquantile(q: float) -> float:
        order = np.argsort(values)
        cw = np.cumsum(weights[order]) / weights.sum()
        return float(values[order][np.searchsorted(cw, q)])

    tau_m = round(wquantile(conf["q_m"]), 4)
    tau_k = round(min(wquantile(conf["q_k"]), tau_m), 4)
    figures = {}
    for name in D:
        entry = {"kind": kinds[name]}
        for label, table in (("any_step", any_step), ("same_step", same_step)):
            s, y = cal[name] if table is any_step else samples(name, same_step)
            entry[label] = {"before": set_figures(s, y, old["tau"]), "after": set_figures(s, y, tau),
                            "n_left_out": int(table[name]["label"].isna().sum())}
        entry["consecutive_q"] = {"q_m": float(np.quantile(consec[name], conf["q_m"])),
                                  "q_k": float(np.quantile(consec[name], conf["q_k"])), "n": int(consec[name].size)}
        figures[name] = entry

    print(f"tau {old['tau']:.4f} -> {tau:.4f} (largest with recall >= {conf['min_recall']} on every set); "
          f"tau_m {old['tau_m']:.4f} -> {tau_m:.4f}, tau_k {old['tau_k']:.4f} -> {tau_k:.4f} "
          f"(consecutive-frame quantiles of {', '.join(mem_sets)})")
    _print_figures(figures, conf)
    result = {
        "thresholds": {"tau": tau, "tau_m": tau_m, "tau_k": tau_k},
        "previous": old,
        "rule": {"tau": f"largest tau (rounded down to 4 decimals) with recall >= {conf['min_recall']} on every set, "
                        "over pairs of views of two robots at any two steps labelled with the co-visibility label "
                        "(overlap >= 0.2 both ways positive, < 0.05 both ways negative, the rest left out)",
                 "tau_m": f"quantile {conf['q_m']} of consecutive-frame similarity, sets weighted equally: {mem_sets}",
                 "tau_k": f"quantile {conf['q_k']} of the same (at most tau_m)"},
        "figures": figures,
        "provenance": {
            "synthetic": {"seeds": list(conf["synth_seeds"]), "preset": conf["synth_preset"],
                          "stride": conf["stride_synth"], "sets": [n for n in D if kinds[n] == "synthetic"]},
            "real": {n: {"manifest": str(m.resolve().relative_to(ROOT)) if m.resolve().is_relative_to(ROOT)
                         else str(m), "manifest_sha": file_digest(m), "stride": conf["stride_real"],
                         "cross_scene_negatives": conf["cross_scene"]}
                     for n, k, _, m in sets if k == "real"},
            "command": conf["command"], "git_revision": git_revision(), "date": time.strftime("%Y-%m-%d"),
            "never": "the paper-default suite (seed 0)"},
        "descriptor_dim": desc.dim,
        "descriptor_conf": knobs.as_dict(desc.conf),
    }
    if paths.samples:
        rows = [t[n].assign(set=n, sample=lab) for lab, t in (("any_step", any_step), ("same_step", same_step))
                for n in D]
        atomic_write_text(paths.samples, pd.concat(rows, ignore_index=True).to_csv(index=False, float_format="%.6g"))
        print(f"wrote {paths.samples}")
    written = None
    if not conf["dry_run"]:
        atomic_write_text(out, json.dumps(result, indent=2, default=float) + "\n")
        print(f"wrote {out}")
        written = out
    print(f"done in {time.perf_counter() - t0:.0f} s")
    return written
