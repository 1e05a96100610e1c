"""benchmarks/bad_pseudoranges.py: the ROC area, the two truth labellings and the tables, on the bundled drive."""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

from lfgnss import datasets
from lfgnss.corrections import geometric_range_m

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bad_pseudoranges as bp  # noqa: E402


@pytest.mark.parametrize("score, positive, want", [
    ([1, 2, 3, 4], [0, 0, 1, 1], 1.0),                 # perfect
    ([1, 2, 3, 4], [1, 1, 0, 0], 0.0),                 # reversed
    ([5, 5, 5, 5], [0, 1, 0, 1], 0.5),                 # all tied: chance
    ([1, 2, 2, 3], [0, 1, 0, 1], 3.5 / 4),             # pairs (2,1) (2,2) (3,1) (3,2): 1 + 0.5 + 1 + 1
    ([0.3, -1.0, 2.0], [1, 0, 0], 0.5),                # one of two negatives below the positive
])
def test_roc_auc_on_hand_cases(score, positive, want):
    assert bp.roc_auc(np.array(score, float), np.array(positive, bool)) == pytest.approx(want)


def test_roc_auc_without_one_class_is_nan_and_bad_input_is_refused():
    assert np.isnan(bp.roc_auc([1.0, 2.0], [True, True]))
    assert np.isnan(bp.roc_auc([1.0, 2.0], [False, False]))
    assert np.isnan(bp.roc_auc([], []))
    with pytest.raises(ValueError, match="finite"):
        bp.roc_auc([1.0, np.nan], [True, False])
    with pytest.raises(ValueError, match="3 scores for 2 labels"):
        bp.roc_auc([1.0, 2.0, 3.0], [True, False])


def test_roc_auc_is_the_pairwise_share_and_the_curve_s_area():
    rng = np.random.default_rng(0)
    score = rng.integers(0, 6, 300).astype(float)                  # many ties
    positive = rng.random(300) < 0.3 + 0.1 * score
    diff = score[positive][:, None] - score[~positive][None, :]
    want = ((diff > 0) + 0.5 * (diff == 0)).mean()
    assert bp.roc_auc(score, positive) == pytest.approx(want)
    fpr, tpr = bp.roc_curve(score, positive)
    assert (fpr[0], tpr[0], fpr[-1], tpr[-1]) == (0.0, 0.0, 1.0, 1.0)
    assert np.sum(np.diff(fpr) * (tpr[1:] + tpr[:-1]) / 2) == pytest.approx(want)


def test_the_strongest_clock_is_that_of_the_three_strongest_with_five_satellites_or_more():
    # constellation 0: three strong clean signals, three weak ones 40 m late; constellation 1: only four satellites
    error = np.array([[0.0, 1.0, 2.0, 40.0, 41.0, 42.0, 1.0, 2.0, 3.0, 4.0]])
    cn0 = np.array([[45.0, 44.0, 43.0, 30.0, 29.0, 28.0, 40.0, 40.0, 40.0, 40.0]])
    system = np.array([[0, 0, 0, 0, 0, 0, 1, 1, 1, 1]])
    ok = np.ones_like(error, bool)
    clock = bp.strongest_clock_m(error, cn0, ok, system, 2)
    assert np.array_equal(clock[0, :6], np.ones(6)) and np.isnan(clock[0, 6:]).all()
    ok[0, 0] = False                                # the strongest left out: the next three, 1, 2 and 40 m
    clock = bp.strongest_clock_m(error, cn0, ok, system, 2)
    assert np.isnan(clock[0, 0]) and np.array_equal(clock[0, 1:6], np.full(5, 2.0))
    ok[0, 1] = False                                # four left: no clock
    assert np.isnan(bp.strongest_clock_m(error, cn0, ok, system, 2)).all()


@pytest.fixture
def clean_sequence(my_drive):
    """The drive's train split with every pseudorange replaced by its true range plus a clock per constellation
    and 1 m of noise, and the slot given +30 m: (sequence, (epoch, slot))."""
    seq = datasets.load_split(my_drive, "train")[0]
    rng = np.random.default_rng(1)
    clock = np.array([1.0e5, 1.0e5 + 37.0])[np.maximum(seq.system_index, 0)]
    true_range = geometric_range_m(seq.sat_pos_ecef_m, np.nan_to_num(seq.truth_ecef_m)[:, None, :])
    pr = np.where(seq.mask, true_range + clock + rng.normal(0.0, 1.0, seq.mask.shape), 0.0)
    ok = seq.mask & seq.labelled[:, None]
    in_gps = ok & (seq.system_index == 0)
    epoch = int(np.flatnonzero(in_gps.sum(axis=1) >= 6)[0])
    slot = int(np.flatnonzero(in_gps[epoch])[0])
    pr[epoch, slot] += 30.0
    return dataclasses.replace(seq, pr_m=pr), (epoch, slot)


def test_an_injected_30_m_delay_is_bad_and_late_under_both_clocks_and_clean_slots_are_not(clean_sequence):
    seq, (epoch, slot) = clean_sequence
    ok = seq.mask & seq.labelled[:, None]
    errors = bp.truth_errors_m(seq)
    assert set(errors) == set(bp.LABELLINGS)
    for name, error in errors.items():
        assert error[epoch, slot] == pytest.approx(30.0, abs=6.0), name
        assert error[epoch, slot] > bp.BAD_M, name                    # bad and late
        others = ok.copy()
        others[epoch, slot] = False
        labelled = others & np.isfinite(error)
        assert labelled.sum() > 0.5 * others.sum(), name
        assert np.abs(error[labelled]).max() < bp.BAD_M, name
        assert np.isnan(error[~ok]).all(), name
    row = bp.summary({f"error {k}": e[ok] for k, e in errors.items()} | {
        "cn0": seq.cn0_dbhz[ok], "vc own model": np.zeros(ok.sum()),
        **{f"cue {c}": -seq.cn0_dbhz[ok] for c in bp.CUES}}, "strongest 3")
    assert (row["n_bad"], row["late"]) == (1, 1.0)


def test_the_tables_run_on_a_registered_dataset(my_drive, tmp_path):
    rows, kept = bp.run([my_drive], ("train", "val"))
    assert [(r["split"], r["labelling"]) for r in rows] == [
        (s, k) for s in ("train", "val", "train+val") for k in bp.LABELLINGS]
    assert all(r["models"] == {"own model": "lfgnss-default.npz", "joint model": "lfgnss-default.npz"} for r in rows)
    pooled = [r for r in rows if r["split"] == "train+val"]
    assert [r["labelled"] for r in pooled] == [sum(r["labelled"] for r in rows if r["labelling"] == p["labelling"]
                                                   and r["split"] != "train+val") for p in pooled]
    train = rows[0]
    assert 0 < train["bad"] < 1 and train["n_bad"] > 0 and 0 <= train["late"] <= 1
    assert all(0 <= train["auc"][c] <= 1 for c in bp.CUES)
    assert train["strong"]["labelled"] < train["labelled"]

    page = bp.markdown(rows, "cmd", (my_drive, "train"))
    assert page.count("### All signals") == 2 and "my-drive train+val" in page and "nan" not in page
    assert "Figure: `figures/bad_pseudoranges.png` (ROC curves, my-drive's train split)." in page
    assert "Figure:" not in bp.markdown(rows, "cmd")                    # no split to draw: none named
    assert bp.plot(kept, tmp_path / "roc.png", my_drive).stat().st_size > 0


def test_the_figure_draws_a_validation_split_where_one_was_run():
    assert bp.shown_split({("a", "train"): 0, ("b", "train"): 0, ("b", "val"): 0}) == ("b", "val")
    assert bp.shown_split({("a", "train"): 0, ("b", "train"): 0}) == ("a", "train")     # --splits train
    assert bp.shown_split({}) is None


def test_the_test_split_is_never_read(my_drive):
    with pytest.raises(ValueError, match="test split"):
        bp.run([my_drive], ("train", "test"))
    with pytest.raises(SystemExit):
        bp.main(["--datasets", my_drive, "--splits", "test"])


def test_unknown_datasets_are_refused_in_one_line(capsys):
    assert bp.main(["--datasets", "nope"]) == 2
    assert capsys.readouterr().err.strip().startswith("bad_pseudoranges.py: unknown dataset nope; known:")


def test_the_windowed_mean_follows_a_slot_that_drops_out_and_comes_back():
    # slot 0 usable at 0 and 1 s, out at 2 and 3 s, back from 3.996 s (a 1 Hz clock's jitter); slot 1 always 5 m
    time = np.array([0.0, 1.0, 2.0, 3.0, 3.996, 5.0, 6.004])
    values = np.stack([[1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0], np.full(7, 5.0)], axis=1)
    usable = np.stack([[True, True, False, False, True, True, True], np.ones(7, bool)], axis=1)
    two = bp.windowed_mean(time, values, usable, 2.0)
    # 3.996 s: the 3 s epoch is in the window but unusable, the 1 and 2 s ones are out: the value alone;
    # 6.004 s: the 3.996 s epoch is 2.008 s back, out of the last 2 s (jitter does not widen the window)
    assert np.array_equal(two[:, 0], [1.0, 1.5, np.nan, np.nan, 16.0, 24.0, 48.0], equal_nan=True)
    assert np.array_equal(two[:, 1], np.full(7, 5.0))
    assert np.array_equal(bp.windowed_mean(time, values, usable, 1.0), np.where(usable, values, np.nan),
                          equal_nan=True)                             # 1 s at 1 Hz: the epoch itself
    assert bp.windowed_mean(time, values, usable, 10.0)[-1, 0] == pytest.approx((1 + 2 + 16 + 32 + 64) / 5)
    with pytest.raises(ValueError, match="must not decrease"):
        bp.windowed_mean(time[::-1], values, usable, 2.0)


def test_the_cauchy_weight_and_the_robust_scale_on_hand_cases():
    assert bp.cauchy_weight(np.array([0.0, bp.CAUCHY_C, -3 * bp.CAUCHY_C])) == pytest.approx([1.0, 0.5, 0.1])
    u = np.array([[0.0, 3.0, -3.0, 30.0, 99.0], [0.1, -0.1, 0.0, 0.2, 99.0], [0.0, 0.0, 0.0, 0.0, 0.0]])
    mask = np.array([[True] * 4 + [False], [True] * 4 + [False], [False] * 5])
    # row 0: |u - 1.5| = 1.5, 1.5, 4.5, 28.5: MAD 3; row 1: tiny, floored; row 2: no slot, the floor
    assert bp.robust_scale(u, mask) == pytest.approx([bp.MAD_TO_SIGMA * 3.0, bp.SCALE_FLOOR, bp.SCALE_FLOOR])


def test_the_robust_fix_down_weights_an_injected_50_m_outlier(my_drive):
    seq = datasets.load_split(my_drive, "train")[0]
    rng = np.random.default_rng(2)
    clock = np.array([1.0e5, 1.0e5 + 37.0])[np.maximum(seq.system_index, 0)]
    true_range = geometric_range_m(seq.sat_pos_ecef_m, np.nan_to_num(seq.truth_ecef_m)[:, None, :])
    pr = np.where(seq.mask, true_range + clock + rng.normal(0.0, 1.0, seq.mask.shape), 0.0)
    in_gps = seq.mask & seq.labelled[:, None] & (seq.system_index == 0)
    epoch = int(np.flatnonzero(in_gps.sum(axis=1) >= 6)[0])
    # the strongest signal: the variance law trusts it most, so the weighted fix follows it furthest
    slot = int(np.argmax(np.where(in_gps[epoch], seq.cn0_dbhz[epoch], -np.inf)))
    pr[epoch, slot] += 50.0
    seq = dataclasses.replace(seq, pr_m=pr)
    weighted, _ = bp.robust_fix(seq, iterations=0)
    fix, weight = bp.robust_fix(seq)
    others = seq.mask[epoch].copy()
    others[slot] = False
    assert fix.ok[epoch] and weight[epoch, slot] < 0.05 and weight[epoch, others].min() > 0.9
    assert fix.residual_m[epoch, slot] == pytest.approx(50.0, abs=3.0)
    assert np.abs(fix.residual_m[epoch, others]).max() < 5.0 < np.abs(weighted.residual_m[epoch, others]).max()
    error_m = [np.linalg.norm(f.pos_ecef_m[epoch] - seq.truth_ecef_m[epoch]) for f in (weighted, fix)]
    assert error_m[1] < 3.0 < 10.0 < error_m[0]


def test_the_far_table_counts_and_scores_signals_more_than_20_m_off():
    error = np.array([0.0, 5.0, -15.0, 25.0, -30.0, np.nan])
    score = np.array([0.0, 1.0, 2.0, 4.0, 3.0, 9.0])
    sig = {f"error {k}": error for k in bp.LABELLINGS} | {"cn0": np.full(6, 40.0), "vc own model": np.zeros(6),
                                                         **{f"cue {c}": score for c in bp.CUES}}
    row = bp.summary(sig, "median")
    assert (row["n_bad"], row["far"]["n_bad"]) == (3, 2) and row["far"]["bad"] == pytest.approx(0.4)
    assert all(row["far"]["auc"][c] == 1.0 for c in bp.CUES) and row["auc"]["C/N0"] == 1.0
    lines = bp.tables([{"dataset": "d", "split": "s", "labelling": "median", **row}], "median")
    assert "### More than 20 m off: all signals" in lines and "| d s | 5 | 2 (40 %) | " + " | ".join(
        ["1.000"] * len(bp.CUES)) + " |" in lines
