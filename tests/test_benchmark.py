"""Benchmark rows (methods), the targets table (target_rows), its columns and its command line (models, datasets)."""
import shutil
from types import SimpleNamespace

import numpy as np
import pytest

from lfgnss import datasets
from lfgnss.benchmark import (DEFAULT_DATASETS, MODEL_DIR, PLAIN, PLAIN_OWN_FILTER, PLAIN_RTS, RTKLIB, _features_for,
                              _select, _trained_on, check_models, main, methods, resolve_datasets, target_rows)
from lfgnss.errors import InputError, print_warning
from lfgnss.metrics import accuracy_table, format_markdown, markdown_table
from lfgnss.sequence import DEFAULT_FEATURES
from lfgnss.solve import SAMPLE_DIR


def test_rows_follow_the_model_files(tmp_path):
    names = [m.name for m in methods(tmp_path, "berlin-pp")]
    assert names == ["least squares (equal weight)", "least squares (C/N0-weighted)", "plain EKF (C/N0 noise, gate)",
                     "plain EKF + RTS smoother"]

    shutil.copy(MODEL_DIR / "lfgnss-default.npz", tmp_path / "lfgnss-default.npz")
    shutil.copy(MODEL_DIR / "lfgnss-default.npz", tmp_path / "lfgnss-no_hem.npz")
    shutil.copy(MODEL_DIR / "lfgnss-transfer-base.npz", tmp_path / "lfgnss-berlin-pp.npz")   # default filter
    rows = {m.name: m for m in methods(tmp_path, "berlin-pp")}
    assert {"LF-GNSS EKF", "LF-GNSS FGO", "LF-GNSS EKF w/o HEM", "LF-GNSS EKF, per-dataset model",
            "LF-GNSS FGO, per-dataset model", "LF-GNSS EKF + RTS smoother",
            "LF-GNSS EKF + RTS smoother, per-dataset model"} <= set(rows)
    assert rows["LF-GNSS EKF + RTS smoother, per-dataset model"].create().smooth
    assert rows["plain EKF + RTS smoother"].create().smooth and not rows[PLAIN].create().smooth
    assert rows["LF-GNSS FGO, per-dataset model"].model == tmp_path / "lfgnss-berlin-pp.npz"
    assert rows["LF-GNSS FGO, per-dataset model"].backend == "fgo"
    # another dataset's own model is not used
    assert not any("per-dataset" in m.name for m in methods(tmp_path, "hk-tst-2019"))
    assert rows["LF-GNSS EKF, per-dataset model"].create().noise.metadata["feature_names"]
    assert PLAIN_OWN_FILTER not in rows            # that model's filter is the default one: no extra row


def test_a_per_dataset_model_in_its_own_filter_brings_the_plain_ekf_in_that_filter(tmp_path):
    """berlin-pp's model was trained with Doppler weights, vertical noise and Huber: the plain EKF gets them too."""
    from estimators.ekf import config_of
    from learning.export import load_model

    shutil.copy(MODEL_DIR / "lfgnss-berlin-pp.npz", tmp_path / "lfgnss-berlin-pp.npz")
    rows = {m.name: m for m in methods(tmp_path, "berlin-pp")}
    plain = rows[PLAIN_OWN_FILTER].create()
    assert rows[PLAIN_OWN_FILTER].model is None and type(plain) is type(rows[PLAIN].create())
    assert plain.config == config_of(load_model(tmp_path / "lfgnss-berlin-pp.npz")) != rows[PLAIN].create().config
    all_rows = [_row("berlin-pp", PLAIN, 35.9, 20.0), _row("berlin-pp", PLAIN_OWN_FILTER, 22.9, 11.2),
                _row("berlin-pp", "LF-GNSS EKF, per-dataset model", 13.3, 8.9),
                _row("berlin-pp", "LF-GNSS FGO, per-dataset model", 12.1, 10.2)]
    bars = {r["method"]: r["3D vs plain EKF"] for r in target_rows(all_rows, [])}
    assert bars == {"LF-GNSS EKF, per-dataset model": "13.30 vs 22.90 (yes)",      # the stronger, same-filter bar
                    "LF-GNSS FGO, per-dataset model": "12.10 vs 35.90 (yes)"}


def test_one_test_sequence_carries_every_feature_the_models_read():
    plain = SimpleNamespace(noise=SimpleNamespace())                        # hand-set noise: no feature names
    extra = SimpleNamespace(noise=SimpleNamespace(feature_names=("cn0", "residual_weighted", "elevation")))
    names = _features_for([plain, extra, extra])
    assert names == DEFAULT_FEATURES + ("residual_weighted",)


def _row(dataset, method, d3, d2):
    return {"dataset": dataset, "method": method, "trained_on": "-", "rmse_3d_m": d3, "rmse_2d_m": d2}


def test_target_rows_compare_each_learned_row_with_its_bars():
    all_rows = [_row("hk-tst-2019", PLAIN, 13.0, 5.0), _row("hk-tst-2019", "LF-GNSS EKF", 9.0, 4.0),
                _row("hk-tst-2019", "LF-GNSS FGO", 12.5, 3.0), _row("hk-tst-2019", "LF-GNSS EKF w/o HEM", 9.5, 4.0),
                _row("hk-tst-2019", PLAIN_RTS, 8.0, 4.0), _row("hk-tst-2019", "LF-GNSS EKF + RTS smoother", 7.0, 3.0)]
    rtk_rows = [_row("hk-tst-2019", "LF-GNSS EKF", 8.0, 3.0), _row("hk-tst-2019", RTKLIB, 8.71, 3.88)]
    rows = {r["method"]: r for r in target_rows(all_rows, rtk_rows)}
    assert set(rows) == {"LF-GNSS EKF", "LF-GNSS FGO", "LF-GNSS EKF + RTS smoother"}   # not ablations, baselines
    ekf, fgo = rows["LF-GNSS EKF"], rows["LF-GNSS FGO"]
    assert ekf["3D vs target"] == "9.00 vs 10.00 (yes)" and ekf["2D vs target"] == "4.00 vs 3.50 (no)"
    assert ekf["3D vs plain EKF"] == "9.00 vs 13.00 (yes)"
    assert ekf["3D vs yardstick"] == "9.00 vs 14.00 (yes)"                  # the yardstick's EKF ...
    assert fgo["3D vs yardstick"] == "12.50 vs 12.20 (no)"                  # ... and its robust graph
    assert ekf["2D vs yardstick"] == "4.00 vs 7.90 (yes)" and fgo["2D vs yardstick"] == "3.00 vs 8.50 (yes)"
    assert ekf["3D vs RTKLIB, its epochs"] == "8.00 vs 8.71 (yes)"
    assert ekf["2D vs RTKLIB, its epochs"] == "3.00 vs 3.88 (yes)"
    assert fgo["3D vs RTKLIB, its epochs"] == "-"                           # no row on RTKLIB's epochs
    rts = rows["LF-GNSS EKF + RTS smoother"]                                # a smoother: against smoothers
    assert rts["3D vs plain EKF"] == "7.00 vs 8.00 (yes)" and rts["3D vs yardstick"] == "7.00 vs 12.20 (yes)"
    assert "| 3D vs target |" in markdown_table(list(rows.values()))


def test_the_solved_column_counts_the_solved_labelled_epochs():
    truth = np.zeros((4, 3)) + [3.7e6, 0.9e6, 5.0e6]           # a point near the Earth's surface
    row = accuracy_table(truth + 1.0, truth, np.array([True, True, False, True]), dataset="d", method="m")
    kept = _select([row | {"trained_on": "-", "epochs_per_s": 1.0}])[0]
    assert kept["n_solved"] == 3 and kept["n_labelled"] == 4
    header, _, cells = format_markdown([kept]).splitlines()
    assert dict(zip(header.split(" | "), cells.split(" | ")))["solved"] == "3"


def test_a_model_file_takes_the_shipped_models_rows_on_every_dataset(tmp_path):
    model = tmp_path / "model.npz"
    shutil.copy(MODEL_DIR / "lfgnss-hk-tst-2019.npz", model)       # a fine-tuned model: trained_on says so
    for dataset_id in ("berlin-pp", "my-drive"):
        rows = {m.name: m for m in methods(model, dataset_id)}
        learned = {n: m for n, m in rows.items() if m.model is not None}
        label = f"({tmp_path.name})"                # named by its folder, as lfgnss.solve names outputs
        assert set(learned) == {f"LF-GNSS EKF {label}", f"LF-GNSS EKF + RTS smoother {label}",
                                f"LF-GNSS FGO {label}"}
        assert {m.model for m in learned.values()} == {model}
    trained = _trained_on(rows[f"LF-GNSS EKF {label}"].create().noise)
    assert trained.startswith("hk-tst-2019 (train), fine-tuned from")
    assert check_models(model, ["berlin-pp"]) == []


def test_a_models_folder_names_what_it_does_not_use(tmp_path):
    shutil.copy(MODEL_DIR / "lfgnss-default.npz", tmp_path / "model.npz")
    with pytest.raises(InputError, match=r"no model file for berlin-pp.*lfgnss-default\.npz.*holds only model\.npz"
                                         r".*--models .*model\.npz"):
        check_models(tmp_path, ["berlin-pp"])
    shutil.copy(MODEL_DIR / "lfgnss-default.npz", tmp_path / "lfgnss-default.npz")
    shutil.copy(MODEL_DIR / "lfgnss-default.npz", tmp_path / "lfgnss-hk-tst-2019.npz")   # a known id: not warned
    warned = check_models(tmp_path, ["berlin-pp"])
    assert len(warned) == 1 and "not using model.npz" in warned[0] and "lfgnss-berlin-pp.npz" in warned[0]
    assert check_models(MODEL_DIR, list(DEFAULT_DATASETS)) == []    # the bundled folder: as before, no warning
    with pytest.raises(InputError, match="no such model file or folder"):
        check_models(tmp_path / "nope", ["berlin-pp"])
    (tmp_path / "lfgnss-no_hem.npz").write_bytes(b"not a model")
    with pytest.raises(ValueError, match="lfgnss-no_hem.npz"):     # a bad model file stops the run before it starts
        check_models(tmp_path, ["berlin-pp"])


def test_the_command_line_refuses_a_folder_without_a_model(tmp_path, capsys):
    (tmp_path / "ft").mkdir()
    shutil.copy(MODEL_DIR / "lfgnss-default.npz", tmp_path / "ft" / "model.npz")
    assert main(["berlin-pp", "--models", str(tmp_path / "ft"), "--out", str(tmp_path / "out"), "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and "model.npz" in err
    assert not (tmp_path / "out").exists()


def test_datasets_of_ones_own_are_registered_and_unknown_ids_refused(tmp_path, monkeypatch, capsys, sample_toml):
    monkeypatch.setattr(datasets, "_REGISTRY", {}, raising=False)   # leave no registration behind
    assert main(["my-drive", "--out", str(tmp_path / "out"), "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown dataset 'my-drive'" in err and "berlin-pp" in err and "--register" in err
    toml = sample_toml("my-drive")
    assert resolve_datasets([]) == list(DEFAULT_DATASETS)
    assert resolve_datasets(["my-drive"], [toml]) == ["my-drive"]
    assert resolve_datasets(["berlin-pp"], [toml]) == ["berlin-pp", "my-drive"]   # a registered set runs too
    with pytest.raises(InputError, match="nope.toml"):
        resolve_datasets([], [tmp_path / "nope.toml"])


def test_the_benchmark_runs_a_users_dataset_with_a_users_model(tmp_path, monkeypatch, capsys, sample_toml):
    monkeypatch.setattr(datasets, "_REGISTRY", {}, raising=False)
    shutil.copy(MODEL_DIR / "lfgnss-default.npz", tmp_path / "model.npz")
    out = tmp_path / "out"
    assert main(["my-drive", "--register", str(sample_toml("my-drive")), "--models", str(tmp_path / "model.npz"),
                 "--out", str(out), "--no-plots"]) == 0
    assert capsys.readouterr().err == ""
    table = (out / "results.md").read_text().split("## All labelled test epochs")[1].split("##")[0]
    rows = [line.split(" | ") for line in table.splitlines() if line.startswith("| my-drive")]
    head = table.strip().splitlines()[0].split(" | ")
    ekf = next(dict(zip(head, r)) for r in rows if r[1] == f"LF-GNSS EKF ({tmp_path.name})")
    assert ekf["trained_on"] == "hk-tst-2019+berlin-pp+hk-tst-static-2020 (train)"
    assert int(ekf["solved"]) > 0 and int(ekf["solved"]) <= int(ekf["labelled"])


def test_no_dataset_with_its_files_writes_no_results(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("LFGNSS_SHARED_DATA", str(tmp_path / "no-data"))
    assert main(["berlin-pp", "--out", str(tmp_path / "out"), "--no-plots"]) == 2
    captured = capsys.readouterr()
    assert "berlin-pp: skipped, missing" in captured.out
    assert captured.err.count("\n") == 1 and "no dataset has all its files" in captured.err
    assert not (tmp_path / "out" / "results.md").exists()          # an empty table never replaces docs/results.md


def test_a_test_split_with_a_truth_gap_is_scored_whole_and_an_empty_one_refused(tmp_path, monkeypatch, sample_toml):
    """An unlabelled epoch inside the test split stays in its one piece (load_split) and in the span the benchmark
    solves, which scores every label."""
    from lfgnss.benchmark import whole_test_split

    monkeypatch.setattr(datasets, "_REGISTRY", {}, raising=False)
    lines = (SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt").read_text().splitlines()
    rows = [k for k, line in enumerate(lines) if line.startswith("point3") and 185.0 < float(line.split()[1]) < 186.0]
    del lines[rows[0]]                                             # one truth line gone inside the test split
    (tmp_path / "gt.txt").write_text("\n".join(lines) + "\n")
    datasets.register_toml(sample_toml("gappy", truth="gt.txt"))
    runs = datasets.load_split("gappy", "test")
    span = whole_test_split("gappy", DEFAULT_FEATURES)
    assert len(runs) == 1 and int(span.labelled.sum()) == int(runs[0].labelled.sum()) == len(span) - 1
    assert np.array_equal(span.time_gps_s, runs[0].time_gps_s)
    toml = sample_toml("empty", splits=((0, 150), (150, 180), (5000, 6000)))
    datasets.register_toml(toml)
    with pytest.raises(InputError) as err:            # review: it named the truth file, not the TOML's [splits]
        whole_test_split("empty", DEFAULT_FEATURES)
    assert str(err.value) == (f"{toml}: [splits] axis = 'relative_s', test = [5000, 6000) holds no labelled epoch of "
                              "dataset empty (the labelled epochs span [0, 282.8] on it)")


def test_warm_up_starts_the_filters_earlier_and_scores_the_test_split_only(tmp_path, monkeypatch, sample_toml):
    from lfgnss.benchmark import run, scored_span, whole_test_split

    monkeypatch.setattr(datasets, "_REGISTRY", {}, raising=False)
    datasets.register_toml(sample_toml("drive"))
    cold = whole_test_split("drive", DEFAULT_FEATURES)
    span, k = scored_span("drive", DEFAULT_FEATURES, "val")
    assert k > 0 and len(span) == len(cold) + k and span.time_gps_s[k] == cold.time_gps_s[0]
    rows, _ = run(["drive"], model_dir=tmp_path, plots=False, warm_up="val")
    cold_rows, _ = run(["drive"], model_dir=tmp_path, plots=False)
    by_name = {r["method"]: r for r in rows}
    for r in cold_rows:                                  # the same labelled epochs are scored in both modes
        assert by_name[r["method"]]["n_labelled"] == r["n_labelled"] == int(cold.labelled.sum())
    assert by_name["least squares (equal weight)"]["rmse_3d_m"] == pytest.approx(
        next(r for r in cold_rows if r["method"] == "least squares (equal weight)")["rmse_3d_m"])   # epoch by epoch
    assert by_name[PLAIN]["rmse_3d_m"] != next(r for r in cold_rows if r["method"] == PLAIN)["rmse_3d_m"]
    datasets.register_toml(sample_toml("late", splits=((0, 150), (190, 200), (180, 190))))
    with pytest.raises(InputError, match="--warm-up val needs labelled epochs of that split before the test split"):
        scored_span("late", DEFAULT_FEATURES, "val")


def test_the_warm_up_and_own_runs_write_their_own_results_files(tmp_path, monkeypatch, capsys, sample_toml):
    monkeypatch.setattr(datasets, "_REGISTRY", {}, raising=False)
    monkeypatch.chdir(tmp_path)
    model = tmp_path / "my model.npz"            # a space: the recorded command line must still run as written
    shutil.copy(MODEL_DIR / "lfgnss-default.npz", model)
    assert main(["my-drive", "--register", str(sample_toml("my-drive")), "--models", str(model),
                 "--warm-up", "val", "--no-plots"]) == 0
    text = (tmp_path / "lfgnss-benchmark" / "warm-up-val" / "results.md").read_text()
    assert not (tmp_path / "docs").exists()      # without --out no run writes over the committed results
    assert text.startswith("# lfgnss benchmark results, filters warmed up on the val split")
    assert f"--models '{model}' --warm-up val --no-plots" in text and "No figures (`--no-plots`)." in text


def test_a_dataset_with_bad_files_costs_its_own_rows_only(tmp_path, monkeypatch, capsys, sample_toml):
    monkeypatch.setattr(datasets, "_REGISTRY", {}, raising=False)
    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))
    good = sample_toml("good")
    bad_obs = tmp_path / "bad.obs"
    bad_obs.write_text("this is not RINEX\n")
    bad = tmp_path / "bad.toml"
    bad.write_text(sample_toml("bad").read_text().replace(
        str(SAMPLE_DIR / "Berlin_Potsdamer_Platz.obs.gz"), str(bad_obs)))
    shutil.copy(MODEL_DIR / "lfgnss-default.npz", tmp_path / "model.npz")
    args = ["--models", str(tmp_path / "model.npz"), "--out", str(tmp_path / "out"), "--no-plots"]
    assert main(["bad", "good", "--register", str(bad), "--register", str(good), *args]) == 2
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1 and captured.err.startswith("error: bad: not run (") and "bad.obs" in captured.err
    text = (tmp_path / "out" / "results.md").read_text()
    assert "**Not run** (bad input; the tables leave these datasets out): bad: not run (" in text
    assert f"| good | LF-GNSS EKF ({tmp_path.name}) |" in text and "| bad |" not in text
    for name, obs in (("gone", tmp_path / "nope.obs"), ("folder", tmp_path)):   # missing; a folder (OSError)
        toml = tmp_path / f"{name}.toml"
        toml.write_text(sample_toml(name).read_text().replace(str(SAMPLE_DIR / "Berlin_Potsdamer_Platz.obs.gz"),
                                                             str(obs)))
        assert main([name, "good", "--register", str(toml), "--register", str(good), *args]) == 2
        captured = capsys.readouterr()
        assert captured.err.count("\n") == 1 and captured.err.startswith(f"error: {name}: not run (")
        assert f"{name}.toml" in captured.err and ("is a folder, not a file" in captured.err) == (name == "folder")
        assert f"| good | LF-GNSS EKF ({tmp_path.name}) |" in (tmp_path / "out" / "results.md").read_text()
    (tmp_path / "out" / "results.md").unlink()
    assert main(["bad", "--register", str(bad), *args]) == 2            # nothing ran: no results file at all
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not written: no dataset could be run (bad: not run (" in err
    assert not (tmp_path / "out" / "results.md").exists()


def test_a_toml_without_the_splits_the_run_scores_is_refused_before_the_run(tmp_path, monkeypatch, capsys, sample_toml):
    monkeypatch.setattr(datasets, "_REGISTRY", {}, raising=False)
    path = sample_toml("no-val")
    path.write_text(path.read_text().replace("val = [150, 180]\n", ""))
    assert main(["--register", str(path), "--out", str(tmp_path / "out"), "--no-plots", "--warm-up", "val"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{path}: [splits] has no val, which this command uses" in err
    assert not (tmp_path / "out").exists()


def test_an_estimator_bug_is_not_reported_as_a_dataset_not_run(tmp_path, monkeypatch, sample_toml):
    """Only reading a dataset's files is caught per dataset; an estimator's error ends the run (no results.md row)."""
    import estimators
    from lfgnss.benchmark import run

    monkeypatch.setattr(datasets, "_REGISTRY", {}, raising=False)
    datasets.register_toml(sample_toml("drive"))

    def broken(self, sequence):
        raise ValueError("operands could not be broadcast")

    monkeypatch.setattr(type(estimators.create("plain-ekf")), "solve", broken)
    failed: list[str] = []
    with pytest.raises(ValueError, match="broadcast"):
        run(["drive"], model_dir=tmp_path, plots=False, failed=failed)
    assert failed == []


def test_the_shipped_models_filter_brings_the_plain_ekf_in_that_filter_as_its_bar():
    """The joint model runs in its own filter (vertical noise, Doppler law): its "vs plain EKF" bar is the plain EKF
    in that filter, so the table does not credit the learning with what the filter settings give."""
    from lfgnss.benchmark import PLAIN_MAIN_FILTER, own_filter
    from learning.export import load_model

    rows = {m.name: m for m in methods(MODEL_DIR, "hk-tst-static-2020")}
    assert rows[PLAIN_MAIN_FILTER].options["config"] == own_filter(load_model(MODEL_DIR / "lfgnss-default.npz"))
    table = [_row("x", PLAIN, 30.0, 20.0), _row("x", PLAIN_MAIN_FILTER, 20.0, 10.0), _row("x", "LF-GNSS EKF", 15.0, 9.0)]
    assert target_rows(table, [])[0]["3D vs plain EKF"] == "15.00 vs 20.00 (yes)"


@pytest.mark.parametrize("argv, where", [([], "lfgnss-benchmark/results.md"),
                                         (["--warm-up", "val"], "lfgnss-benchmark/warm-up-val/results.md"),
                                         (["--out", "docs"], "docs/results.md")])
def test_the_default_output_folder_is_never_docs(argv, where, tmp_path, monkeypatch, capsys):
    """Without --out even the run of the bundled models on the three datasets writes lfgnss-benchmark/, not the
    repository's docs/; --out docs still regenerates that. (No data here: the run stops, naming its results file.)"""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("LFGNSS_SHARED_DATA", str(tmp_path / "no-data"))
    assert main(argv + ["--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {where}: not written: no dataset has all its files") and err.count("\n") == 1, err
    assert list(tmp_path.iterdir()) == []                       # stopped before making any folder


def test_the_help_names_the_dataset_ids_and_how_model_files_are_matched(monkeypatch, capsys):
    monkeypatch.setenv("COLUMNS", "1000")                       # argparse wraps at hyphens otherwise
    with pytest.raises(SystemExit) as exit_info:
        main(["--help"])
    shown = capsys.readouterr().out
    assert exit_info.value.code == 0
    assert f"dataset ids: {', '.join(DEFAULT_DATASETS)} (the benchmark datasets of shared/BENCHMARK.md)" in shown
    assert "lfgnss-default.npz gives the shipped model's rows" in shown
    assert "lfgnss-<dataset id>.npz gives the per-dataset model's rows on that dataset only" in shown
    assert "default: lfgnss-benchmark in the current folder" in shown and "--out docs" in shown


def test_a_part_of_the_benchmark_never_replaces_the_committed_results(tmp_path, monkeypatch, capsys, sample_toml):
    """--out docs (the repository's) takes only the whole default run; a dataset subset, a dataset of one's own or
    other models would have left a docs/results.md of that part alone. Refused before any work, in one line."""
    import argparse

    import lfgnss.paths
    from lfgnss.benchmark import _refuse_partial_docs

    monkeypatch.setattr(lfgnss.paths, "REPO_DIR", tmp_path)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(datasets, "_REGISTRY", {})
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "results.md").write_text("committed")
    toml = sample_toml("my-part")
    for out in ("docs", "docs/sub"):
        assert main(["--register", str(toml), "--out", out, "--no-plots"]) == 2
        assert capsys.readouterr().err == (
            f"error: {out}: holds the committed results of the whole default run (all of "
            f"{', '.join(DEFAULT_DATASETS)}, the bundled models); this run (--register {toml}; datasets my-part "
            "only) would replace them with a part: give another --out\n")
    assert (tmp_path / "docs" / "results.md").read_text() == "committed" and not (tmp_path / "docs" / "sub").exists()
    whole = argparse.Namespace(out=tmp_path / "docs", register=[], models=MODEL_DIR)
    assert _refuse_partial_docs(whole, list(DEFAULT_DATASETS)) is None
    with pytest.raises(InputError, match=r"this run \(--models .*other\) would replace"):
        _refuse_partial_docs(argparse.Namespace(out=tmp_path / "docs", register=[], models=tmp_path / "other"),
                             list(DEFAULT_DATASETS))
    assert _refuse_partial_docs(argparse.Namespace(out=tmp_path / "elsewhere", register=[str(toml)], models=MODEL_DIR),
                                ["my-part"]) is None


def test_warnings_during_a_run_are_one_line_each(monkeypatch, capsys):
    """A warning raised while the benchmark runs (a dataset TOML's constellation left out, say) is printed as
    ``warning: ...`` on one line, not Python's two lines with the source line that raised it."""
    import warnings

    import lfgnss.benchmark as bench

    def warns(args, argv):
        warnings.warn("dataset x: constellation(s) J of its systems have no usable observation\nand are left out")
        warnings.warn("deprecated", FutureWarning)                          # ignored, as before
        return 0

    monkeypatch.setattr(bench, "_main", warns)
    assert main(["--no-plots"]) == 0
    assert capsys.readouterr().err == ("warning: dataset x: constellation(s) J of its systems have no usable "
                                       "observation and are left out\n")
    assert warnings.showwarning is not print_warning                         # restored after the run


def test_the_results_file_names_the_code_and_the_model_files_it_was_made_with(tmp_path):
    """results.md says which code and which model files (by content) made its figures: the command alone does not."""
    import hashlib

    from lfgnss import __version__
    from lfgnss.benchmark import model_files, provenance_text, write_report

    used = model_files(MODEL_DIR, ["berlin-pp"])
    assert [m.name for m in used] == ["lfgnss-default.npz", "lfgnss-no_dpc.npz", "lfgnss-no_hem.npz",
                                      "lfgnss-no_dpc_no_hem.npz", "lfgnss-berlin-pp.npz"]    # not the transfer base
    one = tmp_path / "model.npz"
    shutil.copy(MODEL_DIR / "lfgnss-default.npz", one)
    assert model_files(one, ["berlin-pp"]) == [one]
    text = provenance_text([one])
    digest = hashlib.sha256(one.read_bytes()).hexdigest()[:16]
    assert text.startswith(f"Code: lfgnss {__version__}, git ") or "code not in a git checkout" in text
    assert text.endswith(f"Model files (SHA-256, first 16 hex digits): `model.npz` {digest}.")
    rows = [_row("x", PLAIN, 30.0, 20.0)]
    report = write_report(tmp_path / "results.md", rows, [], "python -m lfgnss.benchmark", figures=False,
                          made_by=text)
    assert f"\n\n{text}\n\n## All labelled test epochs" in report.read_text()


def test_the_code_is_clean_when_only_the_runs_own_output_folder_changed(tmp_path):
    """Regenerating the committed docs/ rewrites tracked files; those changes are the run's, not the code's."""
    import subprocess

    from learning.provenance import git_state

    def git(*args):
        subprocess.run(["git", "-C", str(tmp_path), *args], check=True, capture_output=True)

    git("init", "-q")
    (tmp_path / "code.py").write_text("x = 1\n")
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "results.md").write_text("old\n")
    git("add", ".")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "c")
    (tmp_path / "docs" / "results.md").write_text("new\n")
    assert git_state(tmp_path)["dirty"] and not git_state(tmp_path, ignore=(tmp_path / "docs",))["dirty"]
    assert not git_state(tmp_path, ignore=(tmp_path / "docs", "/somewhere/else"))["dirty"]   # outside: no matter
    (tmp_path / "code.py").write_text("x = 2\n")
    assert git_state(tmp_path, ignore=(tmp_path / "docs",))["dirty"]


def test_an_empty_rtklib_table_says_why():
    """RTKLIB ran but its chi-square test rejected every labelled test epoch (the bundled drive's last 20 s): the
    report said "RTKLIB not installed"."""
    from lfgnss.benchmark import _no_rtklib_rows

    ran = [{"dataset": "my-drive", "method": RTKLIB}, {"dataset": "my-drive", "method": "LF-GNSS EKF"}]
    assert _no_rtklib_rows(ran) == ("RTKLIB solved no labelled test epoch of my-drive (its chi-square test rejected "
                                    "them all): no rows.")
    assert _no_rtklib_rows(ran[1:]) == "RTKLIB not installed (or it failed on every dataset): no rows."


def test_rtklib_runs_on_the_constellations_the_other_rows_use(tmp_path, monkeypatch):
    """A dataset without ``systems`` gives RTKLIB the sequence's constellations (it ran GPS alone, while every other
    row used all of them); a dataset's own ``systems`` come first."""
    import lfgnss.rtklib
    from lfgnss.benchmark import rtklib_solution

    asked = []
    monkeypatch.setattr(lfgnss.rtklib, "rtklib_available", lambda: True)
    monkeypatch.setattr(lfgnss.rtklib, "spp_solution", lambda *a, systems, **k: asked.append(systems) or (None, 0.0))
    spec = SimpleNamespace(id="own", obs=[tmp_path / "a.obs"], nav=[tmp_path / "a.nav"], systems=None)
    rtklib_solution(spec, tmp_path, ("G", "R", "E"))
    rtklib_solution(SimpleNamespace(**{**vars(spec), "systems": ("G", "C")}), tmp_path, ("G", "R", "E"))
    rtklib_solution(spec, tmp_path)
    assert asked == [("G", "R", "E"), ("G", "C"), ("G",)]
