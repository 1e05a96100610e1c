"""benchmarks/code_minus_carrier.py: L1 phases read and turned into metres, the arcs and the excess, on the bundled
drive."""
from __future__ import annotations

import gzip
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from lfgnss import datasets
from lfgnss.constants import SPEED_OF_LIGHT_M_S

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import code_minus_carrier as cm  # noqa: E402


def test_l1_wavelengths_follow_the_constellation_and_the_glonass_channel():
    got = cm.l1_wavelengths_m(np.array([["G05", "E11", "R07"], ["R12", "R03", "C10"]]), {"R07": -7, "R12": 6})
    assert got.shape == (2, 3)
    assert got[0, 0] == got[0, 1] == pytest.approx(SPEED_OF_LIGHT_M_S / 1575.42e6)        # 0.1903 m
    assert got[0, 2] == pytest.approx(SPEED_OF_LIGHT_M_S / (1602e6 - 7 * 0.5625e6))      # 0.1876 m
    assert got[1, 0] == pytest.approx(SPEED_OF_LIGHT_M_S / (1602e6 + 6 * 0.5625e6))
    assert np.isnan(got[1, 1]) and np.isnan(got[1, 2])      # no channel number; BeiDou has no L1 phase here


def test_phases_are_matched_by_time_to_a_tenth_of_a_second():
    phases = (np.array([100.0, 100.2, 100.4]), np.array(["G01", "R07"]),
              np.array([[10.0, 20.0], [11.0, np.nan], [12.0, 22.0]]),
              np.array([[False, False], [True, False], [False, False]]))
    time = np.array([100.04, 100.2, 100.33, 100.4])          # 100.33 s rounds to 100.3 s: no phase epoch
    sv = np.array([["G01", "R07", "G02"]] * 4)
    metres, slip = cm.phases_at_epochs_m(time, sv, phases, {"R07": 1})
    lam_g, lam_r = SPEED_OF_LIGHT_M_S / 1575.42e6, SPEED_OF_LIGHT_M_S / (1602e6 + 0.5625e6)
    want = np.array([[10 * lam_g, 20 * lam_r, np.nan], [11 * lam_g, np.nan, np.nan], [np.nan] * 3,
                     [12 * lam_g, 22 * lam_r, np.nan]])
    assert np.allclose(metres, want, equal_nan=True, rtol=1e-15)
    assert slip.tolist() == [[False] * 3, [True, False, False], [False] * 3, [False] * 3]
    assert np.isnan(cm.phases_at_epochs_m(time, sv, phases, {})[0][:, 1]).all()    # GLONASS without its channel


def _arc_cues(cmc_by_epoch, time=None, slip=None):
    cmc = np.asarray(cmc_by_epoch, float)[:, None]
    time = np.arange(cmc.shape[0]) * 0.2 if time is None else np.asarray(time, float)
    slip = np.zeros(cmc.shape, bool) if slip is None else np.asarray(slip, bool)[:, None]
    return cm.arc_cues(time, np.full(cmc.shape, "G01"), np.ones(cmc.shape, bool), cmc, slip)


def test_arcs_break_at_a_gap_a_loss_of_lock_flag_and_a_jump_and_follow_the_satellite_across_slots():
    time = np.array([0.0, 0.2, 0.4, 0.9, 1.6, 1.8, 2.0, 2.2, 2.4])          # 0.5 s gap kept, 0.7 s gap breaks
    cmc = np.array([5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 99.0, 250.0, 251.0])     # +89 m kept, +151 m breaks
    slip = np.zeros(9, bool)
    slip[5] = True                                                         # loss of lock at 1.8 s
    assert _arc_cues(cmc, time, slip)["arc"][:, 0].tolist() == [0, 0, 0, 0, 1, 2, 2, 3, 3]
    assert _arc_cues(cmc, time)["arc"][:, 0].tolist() == [0, 0, 0, 0, 1, 1, 1, 2, 2]
    age = _arc_cues(cmc, time, slip)["age"][:, 0]
    assert np.allclose(age, [0.0, 0.2, 0.4, 0.9, 0.0, 0.0, 0.2, 0.0, 0.2])

    # G01 in slot 0 then slot 1, G02 the other way round, slot 1 unusable at epoch 1: two arcs, one per satellite
    sv = np.array([["G01", "G02"], ["G01", "G02"], ["G02", "G01"], ["G02", "G01"]])
    usable = np.array([[True, True], [True, False], [True, True], [True, True]])
    cmc2 = np.array([[1.0, 50.0], [2.0, np.nan], [51.0, 3.0], [52.0, 4.0]])
    out = cm.arc_cues(np.arange(4) * 0.2, sv, usable, cmc2, np.zeros((4, 2), bool))
    assert out["arc"].tolist() == [[0, 1], [0, -1], [1, 0], [1, 0]]
    assert np.isnan(out["excess"][1, 1]) and np.allclose(out["age"][3], [0.6, 0.6])


def test_a_1_hz_receiver_s_arcs_do_not_break_at_every_epoch():
    assert cm.arc_gap_s(np.arange(0.0, 10.0, 0.2)) == cm.GAP_S                  # 5 Hz: the 0.6 s gap
    assert cm.arc_gap_s(np.array([0.0, 1.0, 1.996, 3.0, 4.004])) == pytest.approx(1.5, abs=0.01)     # 1 Hz, jitter
    time = np.arange(6.0)
    cues = cm.arc_cues(time, np.full((6, 1), "G01"), np.ones((6, 1), bool), np.arange(6.0)[:, None],
                       np.zeros((6, 1), bool), cm.arc_gap_s(time))
    assert np.all(cues["arc"] == 0) and cues["age"][-1, 0] == 5.0


def test_the_excess_is_cmc_above_the_arc_s_lowest_value_so_far_and_over_the_whole_arc():
    out = _arc_cues([5.0, 3.0, 4.0, 1.0, 2.0])
    assert out["excess"][:, 0].tolist() == [0.0, 0.0, 1.0, 0.0, 1.0]
    assert out["whole-arc excess"][:, 0].tolist() == [4.0, 2.0, 3.0, 0.0, 1.0]
    assert np.allclose(out["deviation"][:, 0], [0.0, -1.0, 0.0, -2.25, -1.0])       # less the running mean

    rng = np.random.default_rng(3)          # random walks with gaps: several arcs on two satellites
    time = np.cumsum(np.where(rng.random(400) < 0.03, 1.0, 0.2))
    cmc = np.cumsum(rng.normal(0.0, 2.0, (400, 2)), axis=0)
    out = cm.arc_cues(time, np.array([["G01", "R02"]] * 400), np.ones((400, 2), bool), cmc, np.zeros((400, 2), bool))
    arcs = np.unique(out["arc"])
    assert arcs.size > 10 and (out["excess"] >= 0).all() and (out["whole-arc excess"] >= out["excess"]).all()
    for a in arcs:
        m = out["arc"] == a
        running_min = np.minimum.accumulate(cmc[m])         # row-major order is time order within one satellite
        assert np.array_equal(out["excess"][m] == 0, cmc[m] == running_min)
        assert np.isclose(out["whole-arc excess"][m].min(), 0.0) and out["excess"][m][0] == 0.0


@pytest.fixture
def drive_phases(my_drive):
    """The drive's train split with its L1 phases [m] and arcs: (sequence, phase (T, N) [m], arc cues)."""
    spec = datasets.get(my_drive)
    seq = datasets.load_split(my_drive, "train")[0]
    metres, slip = cm.phases_at_epochs_m(seq.time_gps_s, seq.sv, cm.read_l1_phases(spec.obs[0], spec.systems),
                                         cm.glonass_channels(spec.nav))
    return seq, metres, cm.arc_cues(seq.time_gps_s, seq.sv, seq.mask, seq.pr_m - metres, slip)


def test_the_drive_s_phase_range_rate_is_its_doppler_range_rate(drive_phases):
    seq, metres, cues = drive_phases
    assert np.isfinite(metres[seq.mask]).all()                             # a phase on every usable slot
    rate = np.diff(metres, axis=0) / np.diff(seq.time_gps_s)[:, None]      # [m/s]
    doppler = 0.5 * (seq.prr_m_s[1:] + seq.prr_m_s[:-1])                   # -lambda D, mean of the two epochs
    pairs = (cues["arc"][1:] == cues["arc"][:-1]) & (cues["arc"][1:] >= 0) & seq.prr_mask[1:] & seq.prr_mask[:-1]
    for system in ("G", "R"):
        m = pairs & (seq.system_index[1:] == seq.systems.index(system))
        assert m.sum() > 1000 and np.median(np.abs(doppler[m])) > 100.0, system      # satellites moving fast
        # cycles or a sign left unconverted would be off by hundreds of m/s; each wrong GLONASS channel by 0.03 %
        assert abs(np.median(rate[m] - doppler[m])) < 0.1, system
        assert np.median(np.abs(rate[m] - doppler[m])) < 3.0, system


def test_the_code_minus_carrier_of_a_long_arc_stays_within_tens_of_metres(drive_phases):
    seq, metres, cues = drive_phases
    cmc = seq.pr_m - metres
    for system in ("G", "R"):
        arcs = np.unique(cues["arc"][(cues["arc"] >= 0) & (seq.system_index == seq.systems.index(system))])
        long = [a for a in arcs if np.ptp(seq.time_gps_s[(cues["arc"] == a).any(axis=1)]) >= 100.0]
        assert len(long) >= 2, system               # phases that were not metres would jump and break every epoch
        for a in long:                              # ... while the carrier's own range is some 2e7 m
            assert np.ptp(cmc[cues["arc"] == a]) < 100.0, (system, a)


def test_the_tables_run_on_a_registered_dataset(my_drive):
    rows = cm.run([my_drive], ("train", "val"))
    assert [(r["split"], r["labelling"]) for r in rows] == [
        (s, k) for s in ("train", "val", "train+val") for k in cm.LABELLINGS]
    by = {(r["split"], r["labelling"]): r for r in rows}
    for split in ("train", "val"):
        r = by[(split, "strongest 3")]
        assert 0 < r["n_bad"] < r["labelled"] <= r["usable"] and all(0 <= r["auc"][c] <= 1 for c in cm.CUES)
        assert r["auc"]["C/N0"] > 0.7                   # weak signals are the bad ones, as bad_pseudoranges finds
        assert by[(split, "median")]["labelled"] == r["usable"]      # the median clock labels every usable slot
        assert r["rms"][0.0]["n"] == r["labelled"] > r["rms"][20.0]["n"] > 0
    pooled = by[("train+val", "strongest 3")]
    assert pooled["labelled"] == by[("train", "strongest 3")]["labelled"] + by[("val", "strongest 3")]["labelled"]
    assert by[("val", "median")]["age_s"] > 30.0    # validation spans 30 s: its arcs began in train
    page = cm.markdown(rows, "cmd")
    assert page.count("| --- |") == 4 and "my-drive validation" in page and "nan" not in page


def _rinex_without_l1(tmp_path: Path, epochs: int = 10) -> Path:
    """The bundled drive's first ``epochs`` epochs with its L1 column renamed P1."""
    from lfgnss.solve import SAMPLE_OBS

    lines = gzip.open(SAMPLE_OBS, "rt").read().splitlines()
    epoch = re.compile(r"^ \d\d( [ \d]\d){4} [ \d]\d\.\d{7}  \d")          # a RINEX 2 epoch line
    starts = [i for i, ln in enumerate(lines) if epoch.match(ln)]
    lines = [ln.replace("C1    L1    S1    D1", "C1    P1    S1    D1") if "TYPES OF OBSERV" in ln else ln
             for ln in lines[:starts[epochs]]]
    path = tmp_path / "no-phase.obs"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_a_file_without_l1_phases_reads_empty_and_its_dataset_is_skipped(my_drive, tmp_path, monkeypatch, capsys):
    time, sv, cycles, slip = cm.read_l1_phases(_rinex_without_l1(tmp_path))
    assert time.size == sv.size == cycles.size == slip.size == 0
    monkeypatch.setattr(cm, "read_l1_phases", lambda path, systems=None: (time, sv, cycles, slip))
    assert cm.run([my_drive]) == []
    assert capsys.readouterr().err == "my-drive: skipped, no L1 carrier phase in Berlin_Potsdamer_Platz.obs.gz\n"
    assert cm.main(["--datasets", my_drive]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        "code_minus_carrier.py: no dataset with its files and L1 phases: nothing to score")


def test_the_test_split_is_never_read(my_drive):
    with pytest.raises(ValueError, match="test split"):
        cm.run([my_drive], ("train", "test"))
    with pytest.raises(SystemExit):
        cm.main(["--datasets", my_drive, "--splits", "test"])


def test_unknown_datasets_are_refused_in_one_line(capsys):
    assert cm.main(["--datasets", "nope"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("code_minus_carrier.py: unknown dataset nope; known:")
