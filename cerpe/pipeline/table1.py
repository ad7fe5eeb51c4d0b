"""Table I of the paper: one row per (setting, method) with the paper's metrics, in long form
(CSV, every setting) and in the paper's layout (Markdown, LaTeX: the supplied settings, a short
caption, one line naming the settings left out and why), with this build's notes on the CERPE rows
beside it (``main_results_notes.md``; ``tables/README.md`` says what the rows are).

Reads finished run folders only (:func:`cerpe.pipeline.evaluate.evaluate_runs`); never runs a method.
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Protocol, Sequence

import numpy as np
import pandas as pd

from ..atomicio import AtomicIOError, atomic_write_text, read_json
from .evaluate import e_pos_on_reference_frames, evaluate_runs, summarise
from ..methods import CERPE_METHODS, EXTENSION_METHODS, METHOD_LABELS, UNAVAILABLE

TABLE_METHODS: tuple[str, ...] = ("aliked-lightglue", "sift-ransac", "nope", "co-visnet", "cerpe-wo-em", "cerpe",
                                  "cerpe-graph")  # the last: our extension, not the paper's
EXPECTED_TABLES: tuple[str, ...] = ("main_results.csv", "main_results.md", "main_results.tex",
                                    "main_results_notes.md")


class TableRuns(Protocol):
    """What Table I reads of a :class:`cerpe.pipeline.paper.PaperContext` (which builds on this module).

    ``settings``: one entry per column group, with ``name``, ``status`` (``ok`` or why not) and
    ``detail``; ``run_dirs``: ``(setting, method) -> run folder``; ``models``: the CERPE runs' ``backbone.models``.
    """

    models: str
    settings: Sequence[Any]
    run_dirs: dict[tuple[str, str], Path]


def main_results(ctx: TableRuns) -> pd.DataFrame:
    """Table I, long form: one row per (setting, method) with the paper's metrics.

    Columns: ``setting, method, e_pos_m, e_pos_gt_scale_m, e_rot_rad, success_pct,
    n_frames, success_after_covis_pct, right_pct, e_pos_on_woem_frames_m, status``.
    ``success_after_covis_pct`` (success over the frames at or after the pair's first co-visible
    step), ``right_pct`` (frames with an estimate within 0.3 rad of the true rotation) and
    ``e_pos_on_woem_frames_m`` (``e_pos_m`` over the frames where CERPE w/o EM reports:
    :func:`~cerpe.pipeline.evaluate.e_pos_on_reference_frames`) are not in the paper's layout
    (Markdown, LaTeX). ``status`` is ``ok``, ``not available offline``,
    ``not supplied`` or ``error``; metrics are NaN unless ``ok``. ``df.attrs["caption"]``
    is the caption the Markdown and LaTeX layouts print (:data:`CAPTION`), ``df.attrs["cerpe_row_note"]``
    what this build's CERPE rows ran (:func:`cerpe_row_note` of their ``run.json``).
    """
    ok = [p for p in ctx.run_dirs.values() if (p / "run.json").exists()]
    summ, same = pd.DataFrame(), pd.Series(dtype=float)
    if ok:
        f, _ = evaluate_runs(ok)
        summ = summarise(f, ["setting", "method"]).set_index(["setting", "method"])
        same = e_pos_on_reference_frames(f).set_index(["setting", "method"])["e_pos_on_ref_frames_m"]
    rows = []
    for e in ctx.settings:
        for m in TABLE_METHODS:
            row = {"setting": e.name, "method": m, "e_pos_m": np.nan, "e_pos_gt_scale_m": np.nan,
                   "e_rot_rad": np.nan, "success_pct": np.nan, "n_frames": 0, "success_after_covis_pct": np.nan,
                   "right_pct": np.nan, "e_pos_on_woem_frames_m": np.nan}
            if e.status != "ok":
                row["status"] = f"{e.status}: {e.detail}" if e.detail else e.status
            elif m in UNAVAILABLE:
                row["status"] = "not available offline"
            elif (e.name, m) in summ.index:
                s = summ.loc[(e.name, m)]
                row.update({k: float(s[k]) for k in ("e_pos_m", "e_pos_gt_scale_m", "e_rot_rad", "success_pct",
                                                     "success_after_covis_pct", "right_pct")})
                row["n_frames"] = int(s["n_frames"])
                row["e_pos_on_woem_frames_m"] = float(same.get((e.name, m), np.nan))
                row["status"] = "ok"
            else:
                row["status"] = "error: run missing (see log)"
            rows.append(row)
    df = pd.DataFrame(rows)
    df.attrs["caption"] = CAPTION
    df.attrs["cerpe_row_note"] = cerpe_row_note(ctx.models, recorded_cerpe_configs(ctx))
    return df


def _fmt(v: float, nd: int = 3) -> str:
    return "--" if v is None or not np.isfinite(v) else f"{v:.{nd}f}"


def _cells(r: pd.Series) -> tuple[str, str, str]:
    st = str(r["status"])
    if st == "not available offline":
        return "n/a", "n/a", "n/a"
    if st.startswith("not supplied"):
        return "not supplied", "", ""
    if st.startswith("skipped"):
        return "skipped", "", ""
    if st != "ok":
        return "error", "", ""
    if r["method"] in CERPE_METHODS:
        pos = f"{_fmt(r['e_pos_m'], 2)} / {_fmt(r['e_pos_gt_scale_m'], 2)}†"
    else:
        pos = f"{_fmt(r['e_pos_gt_scale_m'], 2)}†"
    return pos, _fmt(r["e_rot_rad"]), _fmt(r["success_pct"], 1)


# Table I's caption (at most 80 words: tests count them). What the rows are at length, the stand-ins and
# the extension, is in tables/README.md; what this build's CERPE rows ran, in main_results_notes.md.
CAPTION = ("Relative pose accuracy on the supplied settings: e_pos (m) and e_rot (rad) are means over the "
           "evaluated frames with an estimate; Succ. (%) counts a frame without one as a failure. "
           "† translation at ground-truth scale; CERPE rows show predicted / GT scale. n/a: not available "
           "offline. The SuperGlue row is a stand-in and the last row is our extension, not the paper's "
           "(tables/README.md).")
MODELS_NOTES = {
    "offline": "CERPE here uses the offline models (XFeat + SALAD-style descriptor + multi-view "
               "geometry), not VGGT.",
    "paper": "CERPE uses the paper's models (VGGT + SALAD/DINOv2 + Metric3Dv2).",
}


def cerpe_row_note(models: str, cerpe_configs: Sequence[dict]) -> str:
    """What the CERPE rows are, from the configuration trees their runs recorded (``run.json``).

    Says whether the scale step ran (it is skipped for passes whose unit is already the
    metre, ``BackboneOutput.metric_unit``, when ``scale.metric_unit`` is on: the offline
    backbone anchors its passes on the metric depth priors) and through which view ego-motion
    is chained (``odometry.track_previous``: the previous frame; off: keyframes only, the paper's pass),
    and whether the odometry's step-length rule was on (``odometry.max_accel_mps2`` > 0), whether anchor
    verification was (``anchors.verify``) and with it the weak-estimate rule (``anchors.min_inliers`` > 0).
    """
    note = [MODELS_NOTES.get(models, f"CERPE uses the {models!r} models.")]
    get = lambda c, g, k: c.get(g, {}).get(k)  # noqa: E731
    metric = {bool(get(c, "scale", "metric_unit")) for c in cerpe_configs if get(c, "scale", "metric_unit") is not None}
    prev = {bool(get(c, "odometry", "track_previous")) for c in cerpe_configs
            if get(c, "odometry", "track_previous") is not None}
    if metric == {True} and models == "offline":
        note.append("The default CERPE row skips the scale step (s = 1): the offline backbone's passes are "
                    "already metric, anchored on the depth priors (BackboneOutput.metric_unit, "
                    "scale.metric_unit).")
    elif metric == {True}:
        note.append("The scale step is skipped for passes that say they are metric (BackboneOutput.metric_unit); "
                    "the others are scaled by the metric depth.")
    elif metric == {False}:
        note.append("Every pass is scaled by the metric depth (scale.metric_unit off).")
    if prev == {True}:
        note.append("Ego-motion is chained through the previous frame (odometry.track_previous), not only "
                    "through the keyframes as in the paper's pass.")
    elif prev == {False}:
        note.append("Ego-motion is chained through the keyframes, as in the paper's pass (track_previous off).")
    held = {float(get(c, "odometry", "max_accel_mps2")) > 0 for c in cerpe_configs
            if get(c, "odometry", "max_accel_mps2") is not None}
    if held == {True}:
        note.append("A metric ego-motion step far slower than the robot's last steady ones, more than braking "
                    "explains, is held at their speed (odometry.max_accel_mps2; not in the paper).")
    verify = {bool(get(c, "anchors", "verify")) for c in cerpe_configs if get(c, "anchors", "verify") is not None}
    weak = {int(get(c, "anchors", "min_inliers") or 0) for c in cerpe_configs if get(c, "anchors", "verify")}
    if verify == {True}:
        note.append("A direct estimate becomes the pair's anchor only when verified: consistent with the anchor "
                    "propagated to it, or, before one, with a second estimate (anchors.verify; not in "
                    "the paper, where every direct estimate is the anchor); one that disagrees is not reported "
                    "and the anchor is propagated instead.")
        if len(weak) == 1 and min(weak) > 0:
            note.append(f"With an anchor, an estimate on fewer than {min(weak)} registration inliers is not "
                        "reported either (anchors.min_inliers).")
    elif verify == {False}:
        note.append("Every direct estimate is the new anchor, as in the paper (anchors.verify off).")
    if len(metric) > 1 or len(prev) > 1 or len(held) > 1 or len(verify) > 1 or len(weak) > 1:
        note.append("These settings differ between the CERPE runs (see their run.json).")
    return " ".join(note)


def recorded_cerpe_configs(ctx: TableRuns) -> list[dict]:
    """The configuration trees the CERPE runs of ``ctx`` recorded (``run.json``), unreadable ones left out."""
    configs = []
    for (_, m), p in sorted(ctx.run_dirs.items()):
        if m in CERPE_METHODS and (p / "run.json").is_file():
            try:
                mc = read_json(p / "run.json", "run.json").get("config", {}).get("method_config", {})
            except AtomicIOError:
                continue
            if isinstance(mc, dict) and isinstance(mc.get("tree"), dict):
                configs.append(mc["tree"])
    return configs


def shown_settings(df: pd.DataFrame) -> list[str]:
    """The settings Table I's layouts show: those supplied and run here (a missing run shows as ``error``)."""
    here = df["status"].isin(["ok", "not available offline"]) | df["status"].str.startswith("error: run missing")
    return list(dict.fromkeys(df.loc[here, "setting"]))


def not_shown_line(df: pd.DataFrame) -> str:
    """One line naming every setting the layouts leave out and why (settings with the same reason share it),
    e.g. ``Not shown: a, b (not supplied: fill datasets_manifest/<name>.yaml and set enabled: true).``"""
    shown = set(shown_settings(df))
    why: dict[str, list[str]] = {}
    for s, st in df.drop_duplicates("setting")[["setting", "status"]].itertuples(index=False):
        if s not in shown:
            why.setdefault(re.sub(rf"(?<![\w-]){re.escape(str(s))}(?![\w-])", "<name>", str(st)), []).append(str(s))
    if not why:
        return ""
    return "Not shown: " + "; ".join(f"{', '.join(names)} ({reason})" for reason, names in why.items()) + "."


def _caption(df: pd.DataFrame, caption: str | None) -> str:
    return caption if caption is not None else df.attrs.get("caption", CAPTION)


def _layout_rows(df: pd.DataFrame, settings: Sequence[str]) -> list[tuple[str, list[str]]]:
    """``(method, cells)`` per row of the paper's layout: three cells per shown setting."""
    rows = []
    for m in TABLE_METHODS:
        cells = []
        for s in settings:
            r = df[(df["setting"] == s) & (df["method"] == m)]
            cells += list(_cells(r.iloc[0])) if len(r) else ["", "", ""]
        rows.append((m, cells))
    return rows


def main_results_markdown(df: pd.DataFrame, caption: str | None = None) -> str:
    """Table I in Markdown: the caption, the supplied settings as column groups (e_pos, e_rot, Succ. each),
    then one line naming the settings left out (:func:`not_shown_line`)."""
    settings = shown_settings(df)
    head = "| Method | " + " | ".join(f"{s}: e_pos (m) | {s}: e_rot (rad) | {s}: Succ. (%)" for s in settings) + " |"
    lines = [f"**Table I.** {_caption(df, caption)}", "", head, "|---|" + "---|" * (3 * len(settings))]
    lines += [f"| {METHOD_LABELS[m]} | " + " | ".join(cells) + " |" for m, cells in _layout_rows(df, settings)]
    left_out = not_shown_line(df)
    return "\n".join(lines) + "\n" + (f"\n{left_out}\n" if left_out else "")


def main_results_latex(df: pd.DataFrame, caption: str | None = None) -> str:
    """Table I in LaTeX (booktabs), the paper's layout: supplied settings only, the others named under it."""
    settings = shown_settings(df)
    esc = lambda s: (str(s).replace("_", r"\_").replace("&", r"\&").replace("%", r"\%")  # noqa: E731
                     .replace("<", r"\textless{}").replace(">", r"\textgreater{}").replace("†", r"$^{\dagger}$"))
    out = [r"\begin{table*}[t]", r"\centering", r"\caption{" + esc(_caption(df, caption)) + r"}",
           r"\label{tab:main_results}", r"\resizebox{\textwidth}{!}{%",
           rf"\begin{{tabular}}{{l{'ccc' * len(settings)}}}",
           r"\toprule",
           "Method & " + " & ".join(rf"\multicolumn{{3}}{{c}}{{{esc(s)}}}" for s in settings) + r" \\",
           " ".join(rf"\cmidrule(lr){{{2 + 3 * k}-{4 + 3 * k}}}" for k in range(len(settings))),
           " & " + " & ".join([r"$e_{\mathrm{pos}}$ (m) $\downarrow$ & $e_{\mathrm{rot}}$ (rad) $\downarrow$ & "
                               r"Succ. (\%) $\uparrow$"] * len(settings)) + r" \\",
           r"\midrule"]
    for m, cells in _layout_rows(df, settings):
        if m == "cerpe-wo-em" or m in EXTENSION_METHODS:
            out.append(r"\midrule")
        out.append(esc(METHOD_LABELS[m]) + " & " + " & ".join(esc(c) for c in cells) + r" \\")
    out += [r"\bottomrule", r"\end{tabular}%", "}"]
    left_out = not_shown_line(df)
    if left_out:
        out.append(r"\par\smallskip{\footnotesize " + esc(left_out) + "}")
    out.append(r"\end{table*}")
    return "\n".join(out) + "\n"


def main_results_notes(df: pd.DataFrame) -> str:
    """``main_results_notes.md``: what this build's rows ran (the part of Table I's notes that depends on
    the runs; ``tables/README.md`` has the rest and points here)."""
    lines = ["# Table I: notes on this build", "",
             "Written by `make paper` (cerpe.pipeline.table1) from the runs' `run.json`; "
             "tables/README.md says what the rows and columns are.", "",
             f"**CERPE rows.** {df.attrs.get('cerpe_row_note', '(no CERPE run)')}", "",
             f"**Settings shown:** {', '.join(shown_settings(df)) or 'none'}."]
    left_out = not_shown_line(df)
    if left_out:
        lines += ["", left_out]
    bad = df[df["setting"].isin(shown_settings(df)) & df["status"].str.startswith("error")]
    for s, m, st in bad[["setting", "method", "status"]].itertuples(index=False):
        lines += ["", f"- {s} / {METHOD_LABELS.get(m, m)}: {st}"]
    return "\n".join(lines) + "\n"


def write_main_results(df: pd.DataFrame, tables_dir: Path) -> list[Path]:
    """``main_results.csv`` (long form, every setting), ``.md`` and ``.tex`` (paper layout) and
    ``main_results_notes.md`` (this build's notes), atomically."""
    tables_dir = Path(tables_dir)
    paths = [tables_dir / n for n in EXPECTED_TABLES]
    atomic_write_text(paths[0], df.to_csv(index=False, float_format="%.6g"))
    atomic_write_text(paths[1], main_results_markdown(df))
    atomic_write_text(paths[2], main_results_latex(df))
    atomic_write_text(paths[3], main_results_notes(df))
    return paths
