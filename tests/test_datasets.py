"""Dataset layer: benchmark splits and truth alignment on shared data, user TOML datasets, bad truth lines."""
import dataclasses
import re
import warnings

import numpy as np
import pytest

from lfgnss import datasets
from lfgnss.errors import InputError
from lfgnss.solve import SAMPLE_DIR

# epochs per split from shared/BENCHMARK.md (berlin: 5 Hz epochs with t < 150 s etc.)
EXPECTED = {"hk-tst-2019": {"train": 240, "val": 60, "test": 185},
            "berlin-pp": {"train": 724, "val": 148, "test": 500},
            "hk-tst-static-2020": {"train": 500, "val": 100, "test": 386}}


@pytest.mark.parametrize("dataset_id", sorted(EXPECTED), ids=str)
def test_benchmark_split_alignment(dataset_id):
    spec = datasets.get(dataset_id)
    if spec.missing():
        pytest.skip(f"shared data not found: {spec.missing()[0]}")
    seq = datasets.build(dataset_id)
    counts = {split: int(datasets.split_index(seq, spec, split).sum()) for split in spec.splits}
    assert counts == EXPECTED[dataset_id]
    # aligned truth is close to the coarse fix (tens of metres in these canyons, never kilometres)
    both = np.all(np.isfinite(seq.truth_ecef_m), 1) & np.all(np.isfinite(seq.coarse_ecef_m), 1)
    err = np.linalg.norm(seq.coarse_ecef_m[both] - seq.truth_ecef_m[both], axis=1)
    assert np.median(err) < 120.0
    test = datasets.load_split(dataset_id, "test")
    assert len(test) == 1 and len(test[0]) == EXPECTED[dataset_id]["test"]
    assert np.all(np.isfinite(test[0].truth_ecef_m))


def _user_toml(sample_toml, truth_name="Berlin_Potsdamer_Platz_GT.txt"):
    return sample_toml("my-berlin", truth=truth_name, splits=((0, 100), (100, 120), (120, 300)))


def test_user_dataset_from_toml(tmp_path, monkeypatch, sample_toml):
    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))
    (tmp_path / "Berlin_Potsdamer_Platz_GT.txt").write_text((SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt").read_text())
    spec = datasets.register_toml(_user_toml(sample_toml))
    assert spec.id in datasets.registered()
    train = datasets.load_split("my-berlin", "train")
    test = datasets.load_split("my-berlin", "test")
    assert len(train) == 1 and 450 < len(train[0]) < 520
    assert np.all(np.isfinite(test[0].truth_ecef_m))
    assert train[0].time_gps_s[-1] < test[0].time_gps_s[0]
    # second build comes from the cache
    assert list((tmp_path / "cache" / "sequences").glob("my-berlin-*.npz"))
    val = datasets.load_split("my-berlin", "val")
    both = datasets.load_split("my-berlin", "train+val")          # adjacent splits: one unbroken sequence
    assert len(both) == 1 and both[0].name == "my-berlin/train+val"
    np.testing.assert_array_equal(both[0].time_gps_s, np.concatenate([train[0].time_gps_s, val[0].time_gps_s]))
    apart = datasets.load_split("my-berlin", "train+test")        # val between them: two pieces
    assert [s.name for s in apart] == ["my-berlin/train+test#0", "my-berlin/train+test#1"]
    np.testing.assert_array_equal(apart[0].time_gps_s, train[0].time_gps_s)
    np.testing.assert_array_equal(apart[1].time_gps_s, test[0].time_gps_s)
    with pytest.raises(KeyError, match="has no split 'valid'"):
        datasets.load_split("my-berlin", "train+valid")


def test_training_registers_user_datasets_named_in_its_config(tmp_path, monkeypatch, sample_toml):
    """learning.train's data.register lets the trainer (and its CLI) load a user dataset by id."""
    from learning.train import load_config, load_sequences

    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(datasets, "_REGISTRY", {})
    (tmp_path / "Berlin_Potsdamer_Platz_GT.txt").write_text((SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt").read_text())
    config = load_config(None, [f'data.register=["{_user_toml(sample_toml)}"]', 'data.datasets=["my-berlin"]'])
    assert "my-berlin" not in datasets.registered()
    val = load_sequences("my-berlin", "val", config)
    assert "my-berlin" in datasets.registered() and len(val) == 1 and 90 < len(val[0]) < 110


def test_training_refuses_a_truth_kilometres_from_the_fixes(tmp_path, monkeypatch, sample_toml):
    """A truth of another place (here the drive's truth moved 100 km) warned when built and was trained on all the
    same: learning.train refuses it, naming the distance."""
    from learning.train import load_config, load_sequences

    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(datasets, "_REGISTRY", {})
    rows = [line.split() for line in (SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt").read_text().splitlines()]
    far = [" ".join(r[:2] + [f"{float(r[2]) + 1e5:.4f}"] + r[3:]) for r in rows]
    (tmp_path / "Berlin_Potsdamer_Platz_GT.txt").write_text("\n".join(far) + "\n")
    config = load_config(None, [f'data.register=["{_user_toml(sample_toml)}"]', 'data.datasets=["my-berlin"]'])
    with pytest.raises(ValueError, match=r"my-berlin/val: the truth lies a median 10\d\.\d km from the receiver's "
                                         r"coarse fixes .* training would learn from wrong labels"):
        load_sequences("my-berlin", "val", config)


def test_truth_file_with_bad_lines(tmp_path, sample_toml):
    lines = (SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt").read_text().splitlines()
    lines[2] = "point3 0.5 37851x5.7 899901.8 5037236.1 0 0 0"
    lines[5] = "garbage"
    lines[6] = "# a comment"
    bad = tmp_path / "gt.txt"
    bad.write_text("\n".join(lines))
    spec = datasets.register_toml(_user_toml(sample_toml, "gt.txt"))
    t = spec.time_origin_gps_s + np.array([0.0, 0.5, 0.7])
    truth, notes = datasets.align_truth(t, spec)
    assert notes == [f"{bad}:3: unreadable truth line, skipped", f"{bad}:6: not a point3 record, skipped"]
    assert np.all(np.isfinite(truth[0])) and np.all(np.isnan(truth[1])) and np.all(np.isfinite(truth[2]))


@pytest.mark.parametrize("reader, rows, reason", [
    (datasets.read_urbannav, ["2051 46701 22.3 114.1 10", "2051 46702 95.0 114.1 10", "2051 46703 22.3 114.1 1e308"],
     ["latitude 95 deg outside [-90, 90]", "height 1e+308 m outside [-10000, 100000]"]),
    (datasets.read_ecef_csv, ["1e9 -2418000 5386000 2405000", "1e9 1 2 3", "1e9 1e308 0 0"],
     ["ECEF position 3.74166 m from the Earth's centre, outside [6e+06, 6.6e+06]",
      "ECEF position 1e+308 m from the Earth's centre, outside [6e+06, 6.6e+06]"]),
], ids=["urbannav", "ecef-csv"])
def test_truth_rows_off_the_earth_are_skipped_with_a_note(tmp_path, reader, rows, reason):
    """Readable but impossible truth (a latitude of 95 deg, a height of 1e308 m) is no truth: skipped with a note
    naming file and line; a file of nothing else is a one-line error naming the first line and why."""
    path = tmp_path / "truth.csv"
    path.write_text("\n".join(rows) + "\n")
    spec = datasets.DatasetSpec(id="x", obs=(path,), nav=(path,), truth=path, truth_format="urbannav")
    _, xyz, notes = reader(path, spec)
    assert len(xyz) == 1 and np.isfinite(xyz).all()
    assert notes == [f"{path}:2: {reason[0]}, skipped", f"{path}:3: {reason[1]}, skipped"]
    path.write_text("\n".join(rows[1:]) + "\n")
    with pytest.raises(InputError, match=f"^{re.escape(f'{path}:1: no readable ground-truth line; the first: {reason[0]}')}$"):
        reader(path, spec)


@pytest.mark.parametrize("given, rows, hint", [
    ("smartloc", ["2051,46701,22.3,114.1,10", "2051,46702,22.3,114.1,10"], "urbannav"),
    ("urbannav", ["point3 0.0 3785185.7 899901.8 5037236.1"], "smartloc"),
    ("static", ["1.2e9, -2418000, 5386000, 2405000"], "ecef-csv"),
    ("urbannav", ["345600.0 345600.0 22.3 114.1 10"], "static"),       # a time of week is no GPS week
], ids=["urbannav-as-smartloc", "smartloc-as-urbannav", "ecef-as-static", "static-as-urbannav"])
def test_a_wrong_truth_format_is_named_with_the_one_the_file_reads_as(tmp_path, given, rows, hint):
    path = tmp_path / "truth.txt"
    path.write_text("\n".join(rows) + "\n")
    spec = datasets.DatasetSpec(id="x", obs=(path,), nav=(path,), truth=path, truth_format=given)
    expected = f"(read as truth format {given!r}; the file reads as {hint!r}: give --truth-format {hint})"
    with pytest.raises(InputError, match=re.escape(expected) + "$") as err:
        datasets.align_truth(np.array([1.2e9]), spec)
    assert str(err.value).startswith(f"{path}:1: no readable ground-truth line")
    toml = tmp_path / "my.toml"                      # a dataset TOML's spec: the key to change, where
    with pytest.raises(InputError, match=re.escape(f'give format = "{hint}" in [truth] of {toml})') + "$"):
        datasets.align_truth(np.array([1.2e9]), dataclasses.replace(spec, source=toml))
    path.write_text("nothing here\n")               # no format reads it: no hint, the columns the format wants
    first = "not a point3 record" if given == "smartloc" else "unreadable truth line"
    with pytest.raises(InputError, match=re.escape(f"no readable ground-truth line; the first: {first} "
                                                   f"(truth format {given!r} has rows of {datasets.TRUTH_COLUMNS[given]})")
                       + "$"):
        datasets.align_truth(np.array([1.2e9]), spec)


def test_a_moving_urbannav_file_with_a_bad_week_is_not_told_to_be_static(tmp_path):
    """TOW in milliseconds or a week of -1 fail urbannav's check and read as static rows, but a drive is no point:
    following a 'static' hint would label every epoch with the first row."""
    path = tmp_path / "truth.csv"
    path.write_text("-1,46701000,22.3,114.1,10\n-1,46702000,22.301,114.1,10\n")
    spec = datasets.DatasetSpec(id="x", obs=(path,), nav=(path,), truth=path, truth_format="urbannav")
    with pytest.raises(InputError, match=re.escape("(truth format 'urbannav' has rows of GPS week, ") + ".*[)]$"):
        datasets.align_truth(np.array([1.2e9]), spec)


@pytest.mark.parametrize("row, reason", [
    ("2051.5,46701,22.3,114.1,10", "GPS week 2051.5 is not a whole number in [0, 9999]"),
    ("-1,46701,22.3,114.1,10", "GPS week -1 is not a whole number in [0, 9999]"),
    ("2051,604801,22.3,114.1,10", "time of week 604801 s outside [0, 604800]"),
])
def test_urbannav_rows_need_a_gps_week_and_time_of_week(tmp_path, row, reason):
    assert list(datasets.TRUTH_COLUMNS) == list(datasets.TRUTH_READERS)            # every format says its columns
    path = tmp_path / "truth.csv"
    path.write_text(f"2051,46700,22.3,114.1,10\n{row}\n")
    spec = datasets.DatasetSpec(id="x", obs=(path,), nav=(path,), truth=path, truth_format="urbannav")
    t, xyz, notes = datasets.read_urbannav(path, spec)
    assert len(t) == 1 and notes == [f"{path}:2: {reason}, skipped"]


def test_bad_toml_is_one_line_error(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text('id = "x"\nobs = ["a.obs"]\n')
    with pytest.raises(InputError, match="bad.toml: dataset config lacks"):
        datasets.register_toml(cfg)


def test_present_reports_each_dataset_with_missing_files(tmp_path, monkeypatch):
    monkeypatch.setenv("LFGNSS_SHARED_DATA", str(tmp_path))
    lines = []
    assert datasets.present(["hk-tst-2019", "berlin-pp"], lines.append) == []
    assert [line.split(":")[0] for line in lines] == ["hk-tst-2019", "berlin-pp"]
    assert all("skipped, missing " + str(tmp_path) in line for line in lines)
    for path in datasets.get("berlin-pp").files():                     # now give berlin-pp its files
        path.parent.mkdir(parents=True, exist_ok=True)
        path.touch()
    lines.clear()
    assert datasets.present(["hk-tst-2019", "berlin-pp"], lines.append) == ["berlin-pp"]
    assert len(lines) == 1 and lines[0].startswith("hk-tst-2019: skipped")


# -- user review 15: several obs files, truth defaults as the CLI, static spread, the CLI, str paths --------

BERLIN_ORIGIN_GPS_S = 1900 * 604800 + 126641.7      # first epoch of the bundled Berlin sample


def _toml(tmp_path, name, obs, truth, truth_keys="", dataset_id=None):
    """A smartloc dataset config over the bundled Berlin navigation files."""
    cfg = tmp_path / f"{name}.toml"
    obs_list = ", ".join(f'"{o}"' for o in obs)
    cfg.write_text(f'''id = "{dataset_id or name}"
obs = [{obs_list}]
nav = ["{SAMPLE_DIR / 'brdc1580.16n.gz'}", "{SAMPLE_DIR / 'brdc1580.16g.gz'}"]
systems = ["G", "R"]
[truth]
file = "{truth}"
format = "smartloc"
{truth_keys}
[splits]
axis = "relative_s"
train = [0, 100]
test = [100, 300]
''')
    return cfg


def _split_sample_obs(tmp_path, parts):
    """RINEX 2 files of the bundled sample's epochs [start, stop) per (name, start, stop), each with the header."""
    import gzip
    import re

    lines = gzip.open(SAMPLE_DIR / "Berlin_Potsdamer_Platz.obs.gz", "rt").read().splitlines(keepends=True)
    head = next(i for i, line in enumerate(lines) if "END OF HEADER" in line) + 1
    starts = [i for i in range(head, len(lines))
              if re.match(r" \d\d [ \d]\d [ \d]\d [ \d]\d [ \d]\d [ \d]\d\.\d{7}  \d", lines[i])] + [len(lines)]
    for name, start, stop in parts:
        (tmp_path / name).write_text("".join(lines[:head] + lines[starts[start]:starts[min(stop, len(starts) - 1)]]))


@pytest.fixture
def clean_registry(tmp_path, monkeypatch):
    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(datasets, "_REGISTRY", {})


def test_several_obs_files_are_joined_in_time_order(tmp_path, clean_registry):
    """Defect: only obs[0] was read. Two halves listed out of order build the same Sequence as the whole file."""
    _split_sample_obs(tmp_path, [("a.obs", 0, 700), ("b.obs", 700, 10**6), ("c.obs", 650, 10**6)])
    truth = SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt"
    whole_obs = SAMPLE_DIR / "Berlin_Potsdamer_Platz.obs.gz"
    whole = datasets.build(datasets.register_toml(_toml(tmp_path, "whole", [whole_obs], truth)).id)
    joined = datasets.build(datasets.register_toml(_toml(tmp_path, "joined", ["b.obs", "a.obs"], truth)).id)
    assert len(whole) == 1375 and len(joined) == len(whole)
    np.testing.assert_array_equal(joined.time_gps_s, whole.time_gps_s)
    np.testing.assert_array_equal(joined.truth_ecef_m, whole.truth_ecef_m)
    np.testing.assert_array_equal(joined.pr_m, whole.pr_m)
    np.testing.assert_array_equal(joined.features, whole.features)
    overlapping = datasets.register_toml(_toml(tmp_path, "overlap", ["a.obs", "c.obs"], truth)).id
    with pytest.raises(InputError, match=r"c\.obs: overlaps .*a\.obs in time"):
        datasets.build(overlapping)


def test_toml_truth_defaults_are_the_command_line_ones(tmp_path, clean_registry):
    """Defect: a smartloc TOML without time_origin_gps_s counted from 1980 and matched 0 epochs, silently."""
    obs, truth = SAMPLE_DIR / "Berlin_Potsdamer_Platz.obs.gz", SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt"
    spec = datasets.register_toml(_toml(tmp_path, "no-origin", [obs], truth))
    assert spec.time_origin_gps_s is None and spec.match_tolerance_s == 0.05
    seq = datasets.build(spec.id)
    assert int(seq.labelled.sum()) == 1372                    # as python -m lfgnss.solve on these files
    explicit = datasets.register_toml(
        _toml(tmp_path, "origin", [obs], truth, f"time_origin_gps_s = {BERLIN_ORIGIN_GPS_S}")).id
    np.testing.assert_array_equal(seq.truth_ecef_m, datasets.build(explicit).truth_ecef_m)
    train = datasets.load_split(spec.id, "train")             # relative_s counts from the first epoch too
    assert len(train) == 1 and len(train[0]) == len(datasets.load_split(explicit, "train")[0]) > 450
    # tolerance: 0.5 s as the CLI for every format but smartloc; the built-in specs keep their own
    assert datasets.DatasetSpec("u", ("r.obs",), ("n",), "t.csv", "urbannav").match_tolerance_s == 0.5
    assert {i: (s.match_tolerance_s, s.time_origin_gps_s) for i, s in datasets._builtin().items()} == {
        "hk-tst-2019": (0.5, None), "berlin-pp": (0.05, BERLIN_ORIGIN_GPS_S), "hk-tst-static-2020": (0.5, None)}


def test_truth_matching_no_epoch_warns_with_the_keys_to_check(tmp_path, clean_registry):
    spec = datasets.register_toml(_toml(tmp_path, "origin-zero", [SAMPLE_DIR / "Berlin_Potsdamer_Platz.obs.gz"],
                                        SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt", "time_origin_gps_s = 0"))
    for _ in range(2):                                        # built, then from the cache
        with pytest.warns(UserWarning, match="dataset origin-zero: no truth time .* within 0.05 s .* "
                                             "match_tolerance_s and \\[truth\\] time_origin_gps_s"):
            assert not datasets.build(spec.id).labelled.any()


def test_urbannav_truth_half_a_second_off_matches_by_default(tmp_path):
    truth = tmp_path / "truth.csv"
    truth.write_text("2051,46701.0,22.3,114.17,6.5\n2051,46702.0,22.3,114.17,6.5\n")
    spec = datasets.DatasetSpec("u", (tmp_path / "r.obs",), (tmp_path / "n",), truth, "urbannav")
    t = 2051 * 604800 + np.array([46701.3, 46702.6])
    labelled = np.isfinite(datasets.align_truth(t, spec)[0]).all(axis=1)
    assert labelled.tolist() == [True, False]


def test_truth_is_interpolated_between_rows_but_never_across_a_gap(tmp_path):
    """Defect: a 1 Hz truth on a 5 Hz drive gave each epoch the nearest row, up to 0.5 s of motion off."""
    t0, start = 1_300_000_000.0, np.array([-2_400_000.0, 5_380_000.0, 2_430_000.0])
    rows_t = t0 + np.array([0.0, 1.0, 2.0, 5.0])              # a 3 s gap after t0 + 2
    rows = start + 10.0 * (rows_t - t0)[:, None] * np.array([1.0, 0.0, 0.0])   # 10 m/s along X
    truth = tmp_path / "truth.csv"
    truth.write_text("".join(f"{t:.1f},{x:.3f},{y:.3f},{z:.3f}\n" for t, (x, y, z) in zip(rows_t, rows)))
    spec = datasets.DatasetSpec("e", (tmp_path / "r.obs",), (tmp_path / "n",), truth, "ecef-csv")
    epochs = t0 + np.array([-0.2, 0.0, 0.2, 0.4, 1.0, 1.6, 2.4, 4.8, 5.3, 5.8])
    xyz = datasets.align_truth(epochs, spec)[0]
    labelled = np.isfinite(xyz).all(axis=1)
    assert labelled.tolist() == [True, True, True, True, True, True, True, True, True, False]   # tolerance as before
    inside = np.array([1, 2, 3, 4, 5])                        # between rows 1 s apart: on the true track
    assert np.allclose(xyz[inside, 0] - start[0], 10.0 * (epochs[inside] - t0), atol=1e-6)
    # before the first row, across the 3 s gap and after the last row: the nearest row, as before
    assert np.allclose(xyz[[0, 6, 7, 8]], rows[[0, 2, 3, 3]], atol=1e-6)


def test_build_warns_of_unreadable_truth_lines(tmp_path, clean_registry, sample_toml):
    """Defect: build() threw the reader's notes away; the CLI prints them."""
    lines = (SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt").read_text().splitlines()
    lines[2] = "point3 0.4 37851x5.7 899901.8 5037236.1 0 0 0"
    (tmp_path / "gt.txt").write_text("\n".join(lines))
    spec = datasets.register_toml(_user_toml(sample_toml, "gt.txt"))
    for _ in range(2):                                        # built, then from the cache
        with pytest.warns(UserWarning, match=f"{tmp_path / 'gt.txt'}:3: unreadable truth line, skipped"):
            datasets.build(spec.id)


def test_static_truth_that_is_not_one_point_warns(tmp_path, capsys):
    """Defect: a moving trajectory read as --truth-format static gave hundreds of metres of error, silently."""
    from lfgnss.solve import main

    spec = datasets.DatasetSpec("st", (tmp_path / "r.obs",), (tmp_path / "n",), tmp_path / "one.csv", "static")
    (tmp_path / "one.csv").write_text("270149,270149,22.299915404,114.177707462,4.89\n"
                                      "270150,270150,22.299915410,114.177707462,4.90\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        truth, _ = datasets.align_truth(np.array([0.0, 1.0]), spec)     # one point (1 mm apart): no warning
    assert np.isfinite(truth).all()
    moving = tmp_path / "moving.csv"
    moving.write_text("46701,46701,22.3000,114.1770,6.5\n46702,46702,22.3090,114.1770,6.5\n")   # 1 km north
    with pytest.warns(UserWarning, match=f"{moving}: static truth rows lie up to 99\\d m from the first, not one"):
        datasets.align_truth(np.array([0.0]), datasets.DatasetSpec("st", "r.obs", "n", moving, "static"))
    code = main(["--backend", "wls", "--truth", str(moving), "--truth-format", "static",
                 "--out", str(tmp_path / "o"), "--no-plots", "--quiet"])
    assert code == 0 and f"warning: {moving}: static truth rows lie up to" in capsys.readouterr().err


def test_spec_with_str_paths(tmp_path):
    """Defect: str paths reached Path-only code (AttributeError: 'str' object has no attribute 'read_text')."""
    spec = datasets.DatasetSpec("mine", (str(SAMPLE_DIR / "Berlin_Potsdamer_Platz.obs.gz"),),
                                (str(SAMPLE_DIR / "brdc1580.16n.gz"), str(SAMPLE_DIR / "brdc1580.16g.gz")),
                                str(SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt"), "smartloc")
    assert all(isinstance(p, type(SAMPLE_DIR)) for p in spec.files()) and spec.missing() == []
    truth, notes = datasets.align_truth(BERLIN_ORIGIN_GPS_S + np.array([0.0, 0.3]), spec)
    assert np.isfinite(truth).all() and notes == []


@pytest.mark.parametrize("case", ["no-file", "unknown-id", "bad-axis", "missing-truth"], ids=str)
def test_datasets_cli_bad_input_is_one_line(tmp_path, clean_registry, capsys, case):
    """Defect: tracebacks, a split axis checked only after building, exit 0 when an asked dataset was not built."""
    cfg = _toml(tmp_path, "cli", [SAMPLE_DIR / "Berlin_Potsdamer_Platz.obs.gz"], "truht.csv")
    argv, message = {
        "no-file": (["--register", str(tmp_path / "no.toml")], f"{tmp_path / 'no.toml'}: unreadable dataset config"),
        "unknown-id": (["no-such-id"], "unknown dataset 'no-such-id'; known: "),
        "bad-axis": (["--register", str(cfg)], f"{cfg}: unknown split axis 'gps' in [splits]"),
        "missing-truth": (["--register", str(cfg)], f"dataset not built: cli: missing {tmp_path / 'truht.csv'}"),
    }[case]
    if case == "bad-axis":
        cfg.write_text(cfg.read_text().replace('axis = "relative_s"', 'axis = "gps"'))
    assert datasets.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {message}") and err.count("\n") == 1      # one line, no traceback


def test_datasets_cli_reports_a_dataset_named_twice_once(tmp_path, clean_registry, capsys, sample_toml):
    cfg = _user_toml(sample_toml)
    (tmp_path / "Berlin_Potsdamer_Platz_GT.txt").write_text((SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt").read_text())
    assert datasets.main(["--register", str(cfg), "my-berlin"]) == 0
    out = capsys.readouterr().out
    assert out.count("my-berlin: 1375 epochs, 1372 with truth") == 1
    # a relative_s split says what its seconds count from (review: the first observation epoch was never printed)
    assert ("  val      96 matched epochs, 2016-06-06 11:12:21.7 to 11:12:41.5 GPST (val = [100, 120) on axis "
            "'relative_s', seconds since 2016-06-06 11:10:41.7)\n") in out, out


def test_a_split_that_misses_the_drive_shows_the_drives_span_on_its_axis(clean_registry, capsys, sample_toml):
    """A TOML without a description and with splits on the wrong axis (times of week given on relative_s): the report
    line ends with the systems (it used to end in a dangling '; '), and each empty split says where the drive lies;
    the command then exits 2 (it exited 0, so a script could not tell)."""
    cfg = sample_toml("tow-drive", splits=((126641.7, 126800), (126800, 126850), (126850, 126930)))
    assert datasets.main(["--register", str(cfg)]) == 2
    captured = capsys.readouterr()
    assert captured.err.splitlines()[-1] == ("error: tow-drive: its train split has no epoch with truth; tow-drive: its "
                                             "val split has no epoch with truth; tow-drive: its test split has no "
                                             "epoch with truth (see above)")
    lines = captured.out.splitlines()
    assert lines[0] == "tow-drive: 1375 epochs, 1372 with truth; systems GR"
    assert lines[1] == ("  train     0 matched epochs ([splits] axis = 'relative_s', train = [126641.7, 126800) holds no "
                        "labelled epoch of dataset tow-drive (the labelled epochs span [0, 282.8] on it))")
    cfg.write_text(cfg.read_text().replace('axis = "relative_s"', 'axis = "tow"'))
    datasets.register_toml(cfg)
    assert datasets.main(["--register", str(cfg)]) == 0
    out = capsys.readouterr().out
    assert "  train   765 matched epochs" in out and "(check [splits]" not in out, out
    # each split says when it is and its bounds on the axis (the report showed neither)
    assert re.search(r"  train   765 matched epochs, 2016-06-06 11:10:41\.7 to 11:1\d:\d\d\.\d GPST "
                     r"\(train = \[126641\.7, 126800\) on axis 'tow'\)\n {17}coarse fix for 100\.0%", out), out


@pytest.mark.parametrize("line", ['truth = "truth.csv"', "splits = [1, 2]"])
def test_truth_or_splits_that_are_not_tables_are_one_line_errors(tmp_path, clean_registry, line):
    cfg = tmp_path / "flat.toml"
    cfg.write_text(f'id = "flat"\nobs = ["a.obs"]\nnav = ["a.nav"]\n{line}\n')
    with pytest.raises(InputError, match="must be a table"):
        datasets.register_toml(cfg)


def test_truth_notes_are_summarised_alike_for_the_cli_and_dataset_builds():
    notes = [f"gt.txt:{i}: unreadable truth line, skipped" for i in range(1, 8)]
    assert datasets.truth_note_summary("gt.txt", notes[:5]) == notes[:5]
    assert datasets.truth_note_summary("gt.txt", notes) == notes[:5] + ["gt.txt: 7 unreadable truth lines skipped in all"]


def test_a_split_union_joins_its_parts_and_a_split_named_with_a_plus_stays_itself():
    """split_index("a+b") is the epochs in a or in b, unless the dataset has a split of that very name."""
    import types

    seq = types.SimpleNamespace(labelled=np.array([1, 1, 1, 0, 1, 1, 1, 1], bool), time_gps_s=np.arange(8.0))
    spec = datasets.DatasetSpec(id="x", obs="o", nav="n", truth="t", truth_format="ecef-csv",
                                splits={"a": (0, 2), "b": (5, 6)}, split_axis="epoch")
    assert np.flatnonzero(datasets.split_index(seq, spec, "a+b")).tolist() == [0, 1, 6]   # epoch 3 has no truth: b is epoch 6
    assert np.flatnonzero(datasets.split_index(seq, spec, "b+a")).tolist() == [0, 1, 6]
    named = dataclasses.replace(spec, splits={**spec.splits, "a+b": (2, 4)})
    assert np.flatnonzero(datasets.split_index(seq, named, "a+b")).tolist() == [2, 4]


def test_a_header_line_is_named_as_one(tmp_path):
    truth = tmp_path / "truth.csv"
    truth.write_text("gps_s,x,y,z\n1300000000.0,-2400000.0,5380000.0,2430000.0\nrubbish\n")
    spec = datasets.DatasetSpec("e", (tmp_path / "r.obs",), (tmp_path / "n",), truth, "ecef-csv")
    notes = datasets.align_truth(np.array([1300000000.0]), spec)[1]
    assert notes == [f"{truth}:1: unreadable truth line (a header?), skipped", f"{truth}:3: unreadable truth line, skipped"]


def test_tow_axis_counts_on_across_the_end_of_a_week(monkeypatch):
    """A drive across Saturday/Sunday midnight (GPS) keeps one tow axis: the next week's epochs at 604800 s and on,
    not back at 0, where a split such as [604790, 604810) lost them (and [0, 10) took them)."""
    from types import SimpleNamespace

    t = 1900 * 604800 + 604790.0 + np.arange(0.0, 20.0, 0.5)
    spec = datasets.DatasetSpec("x", (), (), "t.csv", "urbannav", splits={"test": (604795.0, 604805.0)})
    values = datasets.split_axis_values(SimpleNamespace(time_gps_s=t, labelled=np.ones(t.size, bool)), spec)
    np.testing.assert_allclose(values, 604790.0 + np.arange(0.0, 20.0, 0.5), rtol=0)
    monkeypatch.setattr(datasets, "registered", lambda: {"x": spec})
    assert datasets.epochs_in_split("x", "test", t[::-1]) is None      # which week is the first epoch's: unknown
    one_week = datasets.DatasetSpec("y", (), (), "t.csv", "urbannav", splits={"test": (604780.0, 604795.0)})
    monkeypatch.setattr(datasets, "registered", lambda: {"y": one_week})
    assert datasets.epochs_in_split("y", "test", t[::-1]) == 10        # 604790 to 604794.5 s, in any order
    assert datasets.epochs_in_split("y", "test", t[-4:]) == 0          # the next week's epochs alone: none


@pytest.mark.parametrize("axis", ["tow", "relative_s", "epoch"])
def test_split_axis_values_needs_only_times_and_labels(axis):
    """benchmarks/front_end.py --table passes a stand-in with time_gps_s and labelled only; session 49's len(seq) made
    it crash (TypeError: object of type '_SeqLike' has no len())."""
    from types import SimpleNamespace

    t = 1900 * 604800 + 126641.7 + np.arange(4.0)
    truth = np.tile([3783e3, 900e3, 5030e3], (4, 1)).astype(float)
    truth[1] = np.nan
    spec = datasets.DatasetSpec("x", (), (), "t.csv", "urbannav", split_axis=axis, time_origin_gps_s=float(t[0]))
    values = datasets.split_axis_values(SimpleNamespace(time_gps_s=t, labelled=np.isfinite(truth).all(axis=1)), spec)
    expected = {"tow": [126641.7, 126642.7, 126643.7, 126644.7], "relative_s": [0, 1, 2, 3], "epoch": [0, -1, 1, 2]}
    np.testing.assert_allclose(values, expected[axis])


def test_the_builtin_test_splits_run_to_the_end_and_say_so():
    """The berlin-pp and static test splits end with the drive: their bounds printed as [180, 1000000000) (review)."""
    assert datasets.split_bounds_words(datasets.get("berlin-pp"), "test") == "test = [180, inf)"
    assert (datasets.split_bounds_words(datasets.get("hk-tst-static-2020"), "val+test")
            == "val = [500, 600), test = [600, inf)")


def test_a_truth_read_as_pos_in_error_names_the_format_it_reads_as(tmp_path):
    """Review: truth files given as "pos" gave the .pos reader's own errors ("invalid literal for int() with base 10:
    'point3'"), where the other formats say which format the file reads as."""
    truth = SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt"
    spec = datasets.DatasetSpec("x", (SAMPLE_DIR / "Berlin_Potsdamer_Platz.obs.gz",), (), truth, "pos", {}, "tow",
                                ("G", "R"), 0.05)
    with pytest.raises(InputError, match=r"Berlin_Potsdamer_Platz_GT.txt:1: .*\(read as truth format 'pos'; the file "
                                         r"reads as 'smartloc': give --truth-format smartloc\)"):
        datasets.align_truth(np.array([1.149e9]), spec)
    csv = tmp_path / "truth.csv"
    csv.write_text("2016,126641.7,52.5,13.37,70.0\n2016,126641.9,52.5,13.37,70.0\n")
    with pytest.raises(InputError, match=r"truth.csv:1: expected at least 13 fields .*\(read as truth format 'pos'; "
                                         r"the file reads as 'urbannav'"):
        datasets.align_truth(np.array([1.149e9]), dataclasses.replace(spec, truth=csv))


def test_ctrl_c_while_building_is_one_line(capsys, monkeypatch):
    """Review: Ctrl-C during a first build printed a traceback through numpy's savez."""
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(datasets, "alignment_report", interrupted)
    assert datasets.main([]) == 130
    assert capsys.readouterr().err.endswith("interrupted\n")
