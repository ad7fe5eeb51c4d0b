"""Gate metrics (ROC AUC, ROC curve, best-F1 threshold, gate_quality) with known answers."""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cerpe.pipeline.evaluate import best_f1, gate_quality, precision_recall, roc_auc, roc_curve


def test_auc_known_answers():
    y = np.array([0, 0, 1, 1], bool)
    assert roc_auc(np.array([0.1, 0.2, 0.3, 0.4]), y) == 1.0
    assert roc_auc(np.array([0.4, 0.3, 0.2, 0.1]), y) == 0.0
    assert roc_auc(np.array([0.5, 0.5, 0.5, 0.5]), y) == 0.5
    # one of four positive-negative pairs misordered
    assert roc_auc(np.array([0.1, 0.35, 0.3, 0.4]), y) == pytest.approx(0.75)
    assert np.isnan(roc_auc(np.array([0.1, 0.2]), np.array([True, True])))


@settings(max_examples=50, deadline=None)
@given(st.lists(st.tuples(st.floats(-1, 1), st.booleans()), min_size=2, max_size=60))
def test_auc_equals_area_under_curve(pairs):
    s = np.array([p[0] for p in pairs])
    y = np.array([p[1] for p in pairs])
    if y.all() or (~y).all():
        return
    fpr, tpr, thr = roc_curve(s, y)
    assert fpr[0] == tpr[0] == 0 and fpr[-1] == pytest.approx(1) and tpr[-1] == pytest.approx(1)
    assert np.all(np.diff(fpr) >= 0) and np.all(np.diff(tpr) >= 0) and np.all(np.diff(thr) < 0)
    assert np.trapezoid(tpr, fpr) == pytest.approx(roc_auc(s, y), abs=1e-9)


def test_best_f1_and_precision_recall():
    s = np.array([0.9, 0.8, 0.7, 0.2, 0.1])
    y = np.array([1, 1, 0, 0, 0], bool)
    r = best_f1(s, y)
    assert 0.7 < r["tau"] < 0.8 and r["f1"] == 1.0 and r["precision"] == 1.0 and r["recall"] == 1.0
    assert precision_recall(s, y, 0.65) == {"precision": pytest.approx(2 / 3), "recall": 1.0}
    assert np.isnan(precision_recall(s, y, 2.0)["precision"])


def test_gate_quality_from_steps_rows():
    steps = pd.DataFrame({"gate_score": [0.9, 0.6, 0.4, 0.3, np.nan, 0.8],
                          "overlap_gt": [0.5, 0.1, 0.3, 0.0, 0.9, np.nan]})
    q = gate_quality(steps, tau=0.5)
    assert q["n_pairs"] == 4 and q["n_overlapping"] == 2  # NaN rows left out
    assert q["roc_auc"] == pytest.approx(0.75)
    assert q["precision"] == pytest.approx(0.5) and q["recall"] == pytest.approx(0.5)
    assert q["open_rate"] == pytest.approx(0.5) and q["tau"] == 0.5
    assert np.isnan(gate_quality(steps, tau=None)["precision"])


def _two_robot_steps(rows):
    """steps.csv-like rows from ``(step, score, overlap r0->r1, overlap r1->r0)``."""
    out = []
    for step, score, o01, o10 in rows:
        out.append({"encounter": "e", "step": step, "ego": "r0", "other": "r1", "gate_score": score, "overlap_gt": o01})
        out.append({"encounter": "e", "step": step, "ego": "r1", "other": "r0", "gate_score": score, "overlap_gt": o10})
    return pd.DataFrame(out)


def test_symmetric_ceiling_known_answer():
    # step 0 overlaps both ways, step 1 one way only (mixed), steps 2-3 neither
    steps = _two_robot_steps([(0, 0.9, 0.5, 0.5), (1, 0.6, 0.5, 0.1), (2, 0.3, 0.0, 0.0), (3, 0.7, 0.0, 0.0)])
    q = gate_quality(steps, tau=0.5)
    # positives ranked 2, 2, 1 against negatives 1, 0, 0, 0, 0: 14.5 of 15 comparisons won
    assert q["roc_auc_ceiling"] == pytest.approx(14.5 / 15)
    assert q["mixed_share"] == pytest.approx(2 / 8)
    assert q["roc_auc_consistent"] == pytest.approx(1.0)  # 0.9 above 0.3 and 0.7
    assert q["roc_auc"] < q["roc_auc_ceiling"]


def test_symmetric_ceiling_without_pair_columns_is_nan():
    q = gate_quality(pd.DataFrame({"gate_score": [0.9, 0.1], "overlap_gt": [0.5, 0.0]}), tau=0.5)
    assert np.isnan(q["roc_auc_ceiling"]) and np.isnan(q["mixed_share"])


@given(st.integers(0, 10_000))
@settings(max_examples=60, deadline=None)
def test_no_symmetric_score_beats_the_ceiling(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 30))
    o = rng.uniform(0, 0.5, (n, 2))
    sym = rng.uniform(0, 1, n)
    steps = _two_robot_steps([(t, sym[t], o[t, 0], o[t, 1]) for t in range(n)])
    q = gate_quality(steps, tau=0.5)
    if np.isfinite(q["roc_auc"]):
        assert q["roc_auc"] <= q["roc_auc_ceiling"] + 1e-12


def test_covisibility_label_known_answers():
    from cerpe.pipeline.evaluate import covisibility_label

    o_ij = np.array([0.2, 0.5, 0.04, 0.0, 0.3, 0.04, np.nan, 0.19])
    o_ji = np.array([0.2, 0.1, 0.0, 0.049, 0.05, 0.05, 0.5, 0.9])
    got = covisibility_label(o_ij, o_ji)
    np.testing.assert_array_equal(got, [1.0, np.nan, 0.0, 0.0, np.nan, np.nan, np.nan, np.nan])


def test_covisibility_gate_quality_hand_made_example():
    """Unordered pairs: positive both ways >= 0.2, negative both ways < 0.05, the rest left out."""
    steps = _two_robot_steps([(0, 0.9, 0.5, 0.4),     # positive
                              (1, 0.7, 0.3, 0.25),    # positive
                              (2, 0.6, 0.02, 0.01),   # negative
                              (3, 0.3, 0.5, 0.1),     # one way only: left out
                              (4, 0.2, 0.0, 0.0),     # negative
                              (5, 0.4, 0.21, 0.6),    # positive
                              (6, 0.8, 0.3, 0.3)])    # positive; r0's descriptor of r1 lost below
    steps.loc[(steps["step"] == 6) & (steps["ego"] == "r0"), "gate_score"] = np.nan
    q = gate_quality(steps, tau=0.5)
    assert q["covis_n_pairs"] == 6 and q["covis_n_positive"] == 4 and q["covis_n_left_out"] == 1
    # positives 0.9 0.7 0.4 0.8 against negatives 0.6 0.2: 7 of 8 comparisons won
    assert q["covis_roc_auc"] == pytest.approx(7 / 8)
    # open at 0.5: 0.9 0.7 0.8 (right), 0.6 (wrong); 0.4 missed
    assert q["covis_precision"] == pytest.approx(3 / 4) and q["covis_recall"] == pytest.approx(3 / 4)
    assert q["covis_open_rate"] == pytest.approx(4 / 6)
    # the old ordered label is still there, unchanged: 13 ordered rows with a score, 8 overlapping
    assert q["n_pairs"] == 13 and q["n_overlapping"] == 8 and np.isfinite(q["roc_auc"])


def test_covisibility_gate_quality_without_pair_columns_is_empty():
    q = gate_quality(pd.DataFrame({"gate_score": [0.9, 0.1], "overlap_gt": [0.5, 0.0]}), tau=0.5)
    assert q["covis_n_pairs"] == 0 and np.isnan(q["covis_roc_auc"]) and np.isnan(q["covis_recall"])
