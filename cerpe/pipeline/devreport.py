"""The development report's figures (``cerpe dev``), per set and method, read from run folders.

One row per (set, method) (:func:`method_row`):

* ``e_pos_m`` / ``e_pos_gt_scale_m`` (predicted scale / ground-truth scale), ``e_rot_rad``
  mean and ``e_rot_median_rad``, ``success_pct``: the paper's metrics over the evaluated
  frames (:mod:`cerpe.pipeline.evaluate`);
* ``e_pos_on_woem_frames_m`` / ``e_pos_gt_scale_on_woem_frames_m``: ``e_pos_m`` /
  ``e_pos_gt_scale_m`` over the frames where CERPE w/o EM of the same set reports (its
  accepted direct estimates): the methods on the same frames
  (:func:`~cerpe.pipeline.evaluate.e_pos_on_reference_frames`: the graph's e_pos ratio like for like);
* ``success_after_covis_pct``: success over the evaluated frames at or after the pair's
  first co-visible step (ground-truth overlap >= 0.2 both ways);
* ``right_pct``: evaluated frames with an estimate within 0.3 rad of the true rotation
  (success counts any pose, a wrong one too);
* ``n_direct`` / ``n_requests``: evaluated frames with a direct estimate (a placed
  collaborator view) / with an image requested (the gate open and the request policy
  asking; always, for the per-frame baselines);
* ``anchors_rejected`` / ``anchors_replaced`` / ``anchors_weak``: how often the robots counted
  the degradations ``anchor:inconsistent`` / ``anchor:replaced`` / ``anchor:weak`` (0 where the
  algorithm does not have them);
* ``carried_longest_steps``, ``carried_runs_over_3``: wrong estimates carried
  (:func:`wrong_runs`): the longest run of consecutive steps of one ordered pair whose
  estimate is more than 0.3 rad wrong and comes from the same anchor, and how many such
  runs are longer than 3 steps (the target: none). Over every step with an
  estimate and ground truth, evaluated or not;
* ``bytes_per_robot_step``: mean ``bytes_total`` of ``robots.csv`` (everything a robot
  put on the wire per step).

:func:`gate_row` adds the descriptor gate's quality per set from CERPE's ``steps.csv``:
the co-visibility label (``covis_*``) beside the old ordered label. :func:`checks` reads the
table against the development checks (:data:`CHECKS`), one verdict per check and set.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Iterable

import numpy as np
import pandas as pd

from ..runfolder.read import Run, gate_tau, load_run
from .evaluate import REFERENCE_METHOD, RIGHT_ROT_RAD, e_pos_on_reference_frames, frame_errors, gate_quality, summarise
from .textfmt import md_table, text_table

WRONG_RAD = RIGHT_ROT_RAD  # an estimate farther off in rotation is "wrong"
CARRIED_MAX_STEPS = 3  # the target: no wrong estimate carried for more than this many steps
REJECTED = "anchor:inconsistent"
REPLACED = "anchor:replaced"
WEAK = "anchor:weak"

REPORT_COLS: tuple[str, ...] = (
    "set", "method", "e_pos_m", "e_pos_gt_scale_m", "e_pos_on_woem_frames_m", "e_pos_gt_scale_on_woem_frames_m",
    "e_rot_rad", "e_rot_median_rad",
    "success_pct", "success_after_covis_pct", "right_pct", "n_direct", "n_requests", "anchors_rejected", "anchors_replaced",
    "anchors_weak", "carried_longest_steps", "carried_runs_over_3", "bytes_per_robot_step", "n_frames",
    "n_frames_after_covis")
GATE_COLS: tuple[str, ...] = (
    "set", "tau", "covis_roc_auc", "covis_precision", "covis_recall", "covis_n_pairs", "covis_n_positive",
    "covis_n_left_out", "roc_auc", "precision", "recall", "roc_auc_ceiling", "n_pairs", "n_overlapping")


def wrong_runs(steps: pd.DataFrame, wrong_rad: float = WRONG_RAD) -> pd.DataFrame:
    """Runs of wrong estimates carried from one anchor.

    A run is a maximal sequence of consecutive steps of one ordered pair (encounter,
    ego, other) whose estimate's rotation error exceeds ``wrong_rad`` and whose
    ``anchor_step`` is the same (a direct estimate is its own anchor; a row without
    ``anchor_step`` or with -1, e.g. a per-frame baseline, is an anchor of its own).

    Args:
        steps: ``steps.csv`` rows (est_* / gt_* pose columns, ``source``, optional ``anchor_step``).

    Returns:
        One row per run: ``encounter, ego, other, anchor_step, first_step, n_steps``.
    """
    cols = ["encounter", "ego", "other", "anchor_step", "first_step", "n_steps"]
    f = frame_errors(steps, metric_scale=False, every=1)
    f = f[f["success"] & (f["e_rot_rad"] > wrong_rad)].copy()
    if f.empty:
        return pd.DataFrame(columns=cols)
    step = f["step"].astype(int)
    anchor = (pd.to_numeric(f["anchor_step"], errors="coerce").fillna(-1).astype(int)
              if "anchor_step" in f else pd.Series(-1, f.index))
    f["anchor_step"] = np.where(anchor >= 0, anchor, step)
    f = f.assign(step=step).sort_values(["encounter", "ego", "other", "step"], kind="stable")
    key = f["encounter"].astype(str) + "\0" + f["ego"].astype(str) + "\0" + f["other"].astype(str)
    start = ((key != key.shift()) | (f["step"].diff() != 1) | (f["anchor_step"].diff() != 0)).to_numpy()
    f["_run"] = np.cumsum(start)
    g = f.groupby("_run", sort=True)
    out = pd.DataFrame({"encounter": g["encounter"].first(), "ego": g["ego"].first(), "other": g["other"].first(),
                        "anchor_step": g["anchor_step"].first(), "first_step": g["step"].min(),
                        "n_steps": g["step"].size()})
    return out.reset_index(drop=True)[cols]


def carried(runs: pd.DataFrame, longer_than: int = CARRIED_MAX_STEPS) -> dict[str, int]:
    """``carried_longest_steps`` (0 without runs) and ``carried_runs_over_3`` (runs longer than ``longer_than``)."""
    n = runs["n_steps"].to_numpy(int) if len(runs) else np.zeros(0, int)
    return {"carried_longest_steps": int(n.max()) if n.size else 0,
            "carried_runs_over_3": int((n > longer_than).sum())}


def count_degradation(robots: pd.DataFrame, name: str) -> int:
    """How often ``name`` appears in the ``;``-joined ``degradations`` column of ``robots.csv`` rows."""
    if "degradations" not in robots.columns:
        return 0
    return int(sum(str(v).split(";").count(name) for v in robots["degradations"].dropna()))


def method_row(run: Run, set_name: str | None = None, frames: pd.DataFrame | None = None) -> dict:
    """The report's figures (:data:`REPORT_COLS`) of one run folder (``frames``: its
    :func:`frame_errors`, computed here when not given)."""
    if frames is None:
        frames = frame_errors(run.steps, run.metric_scale, run.every)
    s = summarise(frames.assign(_all=0), ["_all"]).iloc[0] if len(frames) else None
    row = {"set": set_name or run.setting, "method": run.method, "e_pos_on_woem_frames_m": float("nan"),
           "e_pos_gt_scale_on_woem_frames_m": float("nan")}
    for k in ("e_pos_m", "e_pos_gt_scale_m", "e_rot_rad", "e_rot_median_rad", "success_pct",
              "success_after_covis_pct", "right_pct"):
        row[k] = float(s[k]) if s is not None else float("nan")
    row["n_frames"] = int(s["n_frames"]) if s is not None else 0
    row["n_frames_after_covis"] = int(s["n_frames_after_covis"]) if s is not None else 0
    row["n_direct"] = int((frames["source"].astype(str) == "direct").sum())
    asked = frames["gate_open"].astype(bool) if "gate_open" in frames else pd.Series(False, index=frames.index)
    if "request_skipped" in frames:  # the request policy may skip an open gate's request
        asked &= ~frames["request_skipped"].fillna(False).astype(bool)
    row["n_requests"] = int(asked.sum())
    row["anchors_rejected"] = count_degradation(run.robots, REJECTED)
    row["anchors_replaced"] = count_degradation(run.robots, REPLACED)
    row["anchors_weak"] = count_degradation(run.robots, WEAK)
    row.update(carried(wrong_runs(run.steps)))
    b = pd.to_numeric(run.robots.get("bytes_total"), errors="coerce")
    row["bytes_per_robot_step"] = float(b.mean()) if b is not None and len(b) else float("nan")
    return {k: row[k] for k in REPORT_COLS}


def run_tau(run: Run) -> float | None:
    """The gate threshold ``tau`` a CERPE run recorded in ``run.json`` (None for the baselines)."""
    return gate_tau(run.meta)


def gate_row(run: Run, set_name: str | None = None) -> dict:
    """The descriptor gate's quality (:data:`GATE_COLS`) over a CERPE run's pairs and steps."""
    q = gate_quality(run.steps, run_tau(run))
    return {"set": set_name or run.setting, **{k: q[k] for k in GATE_COLS if k != "set"}}


def report(runs: Iterable[tuple[str, Path]]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``(table, gate)`` over ``(set name, run folder)`` pairs: :func:`report_runs` of the loaded folders."""
    return report_runs((name, load_run(path)) for name, path in runs)


def report_runs(runs: Iterable[tuple[str, Run]]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``(table, gate)`` over ``(set name, loaded run)`` pairs: :func:`method_row` for every
    run (with ``e_pos_on_woem_frames_m`` over the set's CERPE w/o EM frames), :func:`gate_row`
    for every run of a method with a gate (``cerpe``). A run's ``steps`` may be a replay's
    (``lab/graph_replay.py``)."""
    rows, gates, frames = [], [], []
    for name, run in runs:
        f = frame_errors(run.steps, run.metric_scale, run.every)
        rows.append(method_row(run, name, f))
        frames.append(f.assign(set=name, method=run.method))
        if run.method == "cerpe":
            gates.append(gate_row(run, name))
    table = pd.DataFrame(rows, columns=list(REPORT_COLS))
    if frames and len(table):
        every = pd.concat(frames, ignore_index=True)
        idx = pd.MultiIndex.from_frame(table[["set", "method"]])
        for col, out in (("e_pos_m", "e_pos_on_woem_frames_m"), ("e_pos_gt_scale_m", "e_pos_gt_scale_on_woem_frames_m")):
            same = e_pos_on_reference_frames(every, REFERENCE_METHOD, by=("set",), column=col)
            table[out] = same.set_index(["set", "method"])["e_pos_on_ref_frames_m"].reindex(idx).to_numpy(float)
    return table, pd.DataFrame(gates, columns=list(GATE_COLS))


# --------------------------------------------------------------------------- the development checks
# a back end is never worse than the estimates it fuses: cerpe-graph's e_pos <= this x CERPE's over all frames,
# and <= this x CERPE w/o EM's (the direct estimates) over the frames w/o EM reports
GRAPH_BOUND = 1.0
CHECK_COLS: tuple[str, ...] = ("check", "set", "result", "figures")
# the checks' names, by what each compares (the ``check`` column of report_checks.csv)
REAL_VS_BASELINE = "real set: CERPE vs ALIKED+LG"
WRONG_CARRIED = "wrong estimate carried"
GRAPH_E_POS = "graph e_pos vs CERPE"
GRAPH_E_POS_WOEM_FRAMES = "graph e_pos vs w/o EM, its frames"
GRAPH_E_ROT_SUCCESS = "graph e_rot / success vs CERPE"
GRAPH_CHECKS: tuple[str, ...] = (GRAPH_E_POS, GRAPH_E_POS_WOEM_FRAMES, GRAPH_E_ROT_SUCCESS)
CHECKS: tuple[str, ...] = (REAL_VS_BASELINE, WRONG_CARRIED, *GRAPH_CHECKS)


def _verdict(ok: bool | None) -> str:
    return "n/a" if ok is None else "pass" if ok else "FAIL"


def checks(table: pd.DataFrame, real: Iterable[str] = ()) -> pd.DataFrame:
    """The development checks (:data:`CHECKS`), one row per check and set (:data:`CHECK_COLS`),
    from :func:`report`'s table: a verdict (``pass`` / ``FAIL``, ``n/a`` where a method's row or a
    figure is missing) and the figures it compares, so a stop's claims are one command's output.

    * :data:`REAL_VS_BASELINE` (sets in ``real``): CERPE's success >= ALIKED+LightGlue's and its
      mean and median e_rot <= theirs; the figures add both ``right %`` (estimates within
      :data:`RIGHT_ROT_RAD`), since success counts wrong poses too.
    * :data:`WRONG_CARRIED`: no CERPE estimate more than :data:`WRONG_RAD` rad wrong carried for more
      than :data:`CARRIED_MAX_STEPS` steps.
    * A back end is never worse than the estimates it fuses. :data:`GRAPH_E_POS`: cerpe-graph's e_pos
      (predicted scale; GT scale where the set has none) <= :data:`GRAPH_BOUND` x CERPE's, both over all
      their frames; :data:`GRAPH_E_ROT_SUCCESS`: its e_rot <= CERPE's and its success >= CERPE's.
    * :data:`GRAPH_E_POS_WOEM_FRAMES`: like for like against the direct estimates, over the frames
      CERPE w/o EM reports (``e_pos_on_woem_frames_m``, GT scale where the set has none): cerpe-graph's
      e_pos <= :data:`GRAPH_BOUND` x w/o EM's there.
    """
    real = set(real)
    by = {(str(r["set"]), str(r["method"])): r for _, r in table.iterrows()}
    rows = []

    def fig(r, k, nd=3):
        return _f(float(r[k]), nd) if r is not None else "--"

    for name in dict.fromkeys(table["set"].astype(str)):
        ce, al = by.get((name, "cerpe")), by.get((name, "aliked-lightglue"))
        wo, gr = by.get((name, "cerpe-wo-em")), by.get((name, "cerpe-graph"))
        if name in real:
            ok = None
            if ce is not None and al is not None and np.isfinite([ce["success_pct"], al["success_pct"]]).all():
                rot = [float(r[k]) for r in (ce, al) for k in ("e_rot_rad", "e_rot_median_rad")]
                if float(ce["success_pct"]) < float(al["success_pct"]):
                    ok = False  # also where CERPE has no estimate at all and the baseline some
                elif np.isfinite(rot).all():
                    ok = rot[0] <= rot[2] and rot[1] <= rot[3]
                elif np.isfinite(rot[:2]).all():  # the baseline has no estimate to compare with
                    ok = True
            rows.append({"check": REAL_VS_BASELINE, "set": name, "result": _verdict(ok),
                         "figures": f"success {fig(ce, 'success_pct', 1)} vs {fig(al, 'success_pct', 1)}, e_rot mean "
                                    f"{fig(ce, 'e_rot_rad')} vs {fig(al, 'e_rot_rad')}, median {fig(ce, 'e_rot_median_rad')} "
                                    f"vs {fig(al, 'e_rot_median_rad')}; right % {fig(ce, 'right_pct', 1)} vs "
                                    f"{fig(al, 'right_pct', 1)}"})
        if ce is not None:
            longest = int(ce["carried_longest_steps"])
            rows.append({"check": WRONG_CARRIED, "set": name, "result": _verdict(longest <= CARRIED_MAX_STEPS),
                         "figures": f"longest {longest} steps (bound {CARRIED_MAX_STEPS})"})
        if gr is not None and ce is not None:
            key = "e_pos_m" if np.isfinite(float(gr["e_pos_m"])) else "e_pos_gt_scale_m"
            g, ref = float(gr[key]), float(ce[key])
            ok = None if not np.isfinite([g, ref]).all() else g <= GRAPH_BOUND * ref
            rows.append({"check": GRAPH_E_POS, "set": name, "result": _verdict(ok),
                         "figures": f"{_f(g)} vs {GRAPH_BOUND:g} x {_f(ref)}"
                                    f"{' (GT scale)' if key != 'e_pos_m' else ''}"})
            if wo is not None:
                k2 = "e_pos_on_woem_frames_m" if key == "e_pos_m" else "e_pos_gt_scale_on_woem_frames_m"
                same = (float(gr[k2]), float(wo[k2]))
                ok = None if not np.isfinite(same).all() else same[0] <= GRAPH_BOUND * same[1]
                rows.append({"check": GRAPH_E_POS_WOEM_FRAMES, "set": name, "result": _verdict(ok),
                             "figures": f"{_f(same[0])} vs {GRAPH_BOUND:g} x {_f(same[1])}"
                                        f"{' (GT scale)' if key != 'e_pos_m' else ''}"})
            er = (float(gr["e_rot_rad"]), float(ce["e_rot_rad"]))
            su = (float(gr["success_pct"]), float(ce["success_pct"]))
            ok = None if not all(np.isfinite(er + su)) else er[0] <= er[1] and su[0] >= su[1]
            rows.append({"check": GRAPH_E_ROT_SUCCESS, "set": name, "result": _verdict(ok),
                         "figures": f"e_rot {_f(er[0])} vs {_f(er[1])}, success {_f(su[0], 1)} vs {_f(su[1], 1)}"})
    return pd.DataFrame(rows, columns=list(CHECK_COLS))


# --------------------------------------------------------------------------- formatting
def _f(v: float, nd: int = 3) -> str:
    return "--" if v is None or not np.isfinite(v) else f"{v:.{nd}f}"


def _cells(r: pd.Series) -> list[str]:
    return [str(r["set"]), str(r["method"]), f"{_f(r['e_pos_m'], 3)} / {_f(r['e_pos_gt_scale_m'], 3)}",
            f"{_f(r['e_pos_on_woem_frames_m'])} / {_f(r['e_pos_gt_scale_on_woem_frames_m'])}", _f(r["e_rot_rad"]), _f(r["e_rot_median_rad"]), _f(r["success_pct"], 1),
            _f(r["success_after_covis_pct"], 1), _f(r["right_pct"], 1), f"{int(r['n_direct'])} / {int(r['n_requests'])}",
            f"{int(r['anchors_rejected'])} / {int(r['anchors_weak'])}",
            f"{int(r['carried_longest_steps'])} ({int(r['carried_runs_over_3'])})",
            _f(r["bytes_per_robot_step"], 0), str(int(r["n_frames"]))]


HEADER = ["set", "method", "e_pos m (pred / GT scale)", "e_pos on w/o EM frames (pred / GT)", "e_rot mean", "e_rot med", "succ %", "succ>covis %",
          "right %", "placed / req", "rejected / weak", "wrong carried (>3)", "B/robot/step", "frames"]
GATE_HEADER = ["set", "tau", "covis AUC", "covis P", "covis R", "covis pairs (pos)", "left out",
               "ordered AUC", "ordered P", "ordered R", "ceiling"]


def _gate_cells(r: pd.Series) -> list[str]:
    return [str(r["set"]), _f(r["tau"], 4), _f(r["covis_roc_auc"]), _f(r["covis_precision"]),
            _f(r["covis_recall"]), f"{int(r['covis_n_pairs'])} ({int(r['covis_n_positive'])})",
            str(int(r["covis_n_left_out"])), _f(r["roc_auc"]), _f(r["precision"]), _f(r["recall"]),
            _f(r["roc_auc_ceiling"])]


LEGEND = ("e_pos on w/o EM frames: e_pos (predicted / GT scale) over the frames where CERPE w/o EM reports, "
          "the methods on the same frames; e_rot in rad; succ>covis: success over frames at or after the pair's first step with GT overlap >= 0.2 "
          f"both ways; right: frames with an estimate within {RIGHT_ROT_RAD:g} rad of the true rotation; placed / req: evaluated frames with a direct estimate / with an image requested; rejected / weak: "
          f"'{REJECTED}' / '{WEAK}' counted; wrong carried: longest run of consecutive steps of one pair more than "
          f"{WRONG_RAD} rad wrong from one anchor (runs longer than {CARRIED_MAX_STEPS} steps); B/robot/step: "
          "bytes a robot sent per step. Gate: the descriptor cosine against the co-visibility label (unordered "
          "pair, overlap >= 0.2 both ways positive, < 0.05 both ways negative, the rest left out) at the run's "
          "tau, beside the old ordered label (overlap_gt >= 0.2 per direction) and its symmetric-score ceiling.")


CHECK_HEADER = ["check", "set", "result", "figures (CERPE or cerpe-graph vs the reference)"]


def format_text(table: pd.DataFrame, gate: pd.DataFrame, check: pd.DataFrame | None = None) -> str:
    """The report as fixed-width text (what ``cerpe dev`` prints)."""
    out = [text_table(HEADER, [_cells(r) for _, r in table.iterrows()])]
    if len(gate):
        out += ["", "descriptor gate (CERPE's pairs and steps):",
                text_table(GATE_HEADER, [_gate_cells(r) for _, r in gate.iterrows()])]
    if check is not None and len(check):
        out += ["", "development checks:",
                text_table(CHECK_HEADER, [list(map(str, r)) for r in check.itertuples(index=False)], left=4)]
    return "\n".join(out + ["", LEGEND])


def format_markdown(table: pd.DataFrame, gate: pd.DataFrame, provenance: dict | None = None,
                    check: pd.DataFrame | None = None) -> str:
    """The report as Markdown (tables, legend, and the provenance as a JSON block)."""
    out = ["# cerpe development report", "", md_table(HEADER, [_cells(r) for _, r in table.iterrows()])]
    if len(gate):
        out += ["", "Descriptor gate (CERPE's pairs and steps):", "",
                md_table(GATE_HEADER, [_gate_cells(r) for _, r in gate.iterrows()])]
    if check is not None and len(check):
        out += ["", "Development checks:", "",
                md_table(CHECK_HEADER, [list(map(str, r)) for r in check.itertuples(index=False)])]
    out += ["", LEGEND]
    if provenance:
        out += ["", "```json", json.dumps(provenance, indent=1, sort_keys=True, default=str), "```"]
    return "\n".join(out) + "\n"
