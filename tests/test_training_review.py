"""Session 50's "own data" review of training, export and the benchmark: a resumed run refuses a dataset TOML edited
or removed since it started; --models once, its rows named as lfgnss.solve names outputs; an untrained model is
named by learning.export and the benchmark; an ensemble's recipe is checked before its seeds, with both values;
training's unknown-dataset hint; a model on a sequence of no satellite slot."""
import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

import estimators
import lfgnss
from learning.export import load_model, main as export_main
from learning.train import dataset_toml_change, main as train_main
from lfgnss import datasets
from lfgnss.benchmark import (DEFAULT_DATASETS, MODEL_DIR, RTKLIB, _trained_on, file_label, main as bench_main,
                              methods)
from lfgnss.solve import SAMPLE_NAV, SAMPLE_OBS, SAMPLE_TRUTH, model_tag
from tiny_training import TINY, sets

CONFIG = "learning/configs/default.toml"
DOCS_RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results.md"
#: A dataset TOML the runs register (never read as data: they train on synthetic data), and its edited val split.
TOML_TEXT = 'id = "mine"\nobs = ["x.obs"]\nnav = ["x.nav"]\n[splits]\naxis = "relative_s"\ntrain = [0, 150]\n' \
            'val = [150, 180]\ntest = [180, 200]\n'
UNTRAINED = "holds no training: it is epoch 0 of its run"


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """Two one-epoch runs, seed 0 both: ``full`` (8 features, registering ``mine.toml``) and ``nodpc`` (4)."""
    tmp = tmp_path_factory.mktemp("session50")
    toml = tmp / "mine.toml"
    toml.write_text(TOML_TEXT)
    settings = {"full": [f"data.register=['{toml}']"], "nodpc": ["data.drop_features=['dpc']"]}
    capture = pytest.MonkeyPatch()
    import io
    import sys

    capture.setattr(sys, "stdout", io.StringIO())
    capture.setattr(sys, "stderr", io.StringIO())
    try:
        for name, extra in settings.items():
            assert train_main(["--config", CONFIG, "--out", str(tmp / name), "--no-progress"]
                              + sets(TINY + extra)) == 0
    finally:
        capture.undo()
    return tmp


def _refused(main, argv: list[str], capsys) -> str:
    """The one stderr line of a command that exits 2 on ``argv``."""
    with pytest.raises(SystemExit) as stop:
        main(argv)
    err = capsys.readouterr().err
    assert stop.value.code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    return err


# ------------------------------------------------------------------------ 1: --resume and the dataset TOML

def test_resume_refuses_a_dataset_toml_edited_or_gone_since_the_run_started(runs, capsys):
    toml, out = runs / "mine.toml", runs / "full"
    resume = ["--resume", "--out", str(out), "--set", "train.epochs=2", "--no-progress"]
    try:
        toml.write_text(TOML_TEXT.replace("val = [150, 180]", "val = [150, 170]"))
        err = _refused(train_main, resume, capsys)
        assert f"error: {toml}: splits.val is [150, 170] now, [150, 180] when {out / 'last.pt'} was started; a " \
               "resumed run goes on with the data it was started with" in err
        assert f"put the file back as it was (its text is recorded in the run: python -m learning.export --show " \
               f"{out / 'model.npz'} names it), or start a new --out" in err
        toml.unlink()
        err = _refused(train_main, resume, capsys)
        assert f"error: {toml}: the run in {out} was registered from this dataset TOML, which is missing now; put it " \
               "back as it was to --resume (its text is recorded in the run: python -m learning.export --show" in err
    finally:
        toml.write_text(TOML_TEXT)
    assert torch.load(out / "last.pt", weights_only=False)["epoch"] == 1          # nothing was trained


def test_a_toml_change_is_its_first_changed_key_and_comments_are_none():
    assert dataset_toml_change(TOML_TEXT, "# mine\n" + TOML_TEXT.replace("\n[", "\n\n[")) is None
    assert dataset_toml_change(TOML_TEXT, TOML_TEXT + 'description = "x"\n') == "splits.description is 'x' now, unset"
    assert dataset_toml_change(TOML_TEXT, TOML_TEXT + "[[") == "its text differs from the text it had"
    assert dataset_toml_change(TOML_TEXT, 'description = "my drive"\n' + TOML_TEXT) is None          # no data setting
    # a time_origin_gps_s that nothing read (urbannav truth, tow splits), removed as registration now asks: resumes
    tow = TOML_TEXT.replace('axis = "relative_s"', 'axis = "tow"') + '[truth]\nfile = "t.csv"\n'
    assert dataset_toml_change(tow.replace('file = "t.csv"', 'file = "t.csv"\ntime_origin_gps_s = 5.0'), tow) is None
    truth = TOML_TEXT + '[truth]\nfile = "t.csv"\n'
    assert dataset_toml_change(truth, truth + "time_offset_s = 0\n") is None              # the default, spelt out
    assert dataset_toml_change(truth, truth + "time_offset_s = 18\n") == "truth.time_offset_s is 18 now, unset"
    assert dataset_toml_change(TOML_TEXT + '[truth]\nfile = "t.csv"\ntime_origin_gps_s = 5.0\n',
                        TOML_TEXT + '[truth]\nfile = "t.csv"\n') == "truth.time_origin_gps_s is unset now, 5.0"


# ------------------------------------------------------------------------ 2: --models once, rows by run folder

def test_models_given_twice_is_an_option_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        bench_main(["--models", str(tmp_path / "a.npz"), "--models", str(tmp_path / "b.npz"), "--out",
                    str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert stop.value.code == 2
    assert (f"error: argument --models: given twice ({tmp_path / 'a.npz'}, then {tmp_path / 'b.npz'}); it takes one "
            "model file or folder: to compare two model files, run the benchmark once for each, with its own --out"
            in err)
    assert not (tmp_path / "out").exists()


def test_a_runs_model_file_names_its_rows_by_its_run_folder_as_solve_names_outputs(tmp_path):
    run = tmp_path / "runs" / "ft"
    run.mkdir(parents=True)
    shutil.copy(MODEL_DIR / "lfgnss-default.npz", run / "model.npz")
    shutil.copy(MODEL_DIR / "lfgnss-default.npz", tmp_path / "mine.npz")
    assert file_label(run / "model.npz") == f" ({model_tag(run / 'model.npz')})" == " (ft)"
    assert file_label(tmp_path / "mine.npz") == " (mine)" and file_label(MODEL_DIR) == ""
    names = [m.name for m in methods(run / "model.npz", "berlin-pp")]
    assert {"LF-GNSS EKF (ft)", "LF-GNSS EKF + RTS smoother (ft)", "LF-GNSS FGO (ft)"} <= set(names)


def test_the_bundled_models_rows_are_docs_results_rows_unchanged():
    table = DOCS_RESULTS.read_text().split("## All labelled test epochs")[1].split("\n## ")[0]
    shown = {tuple(c.strip() for c in line.strip("| ").split(" | ")[:3]) for line in table.splitlines()
             if line.startswith("| ") and not line.startswith(("| dataset", "| ---"))}
    made = {(d, m.name, "-" if m.model is None else _trained_on(load_model(m.model)))
            for d in DEFAULT_DATASETS for m in methods(MODEL_DIR, d)}
    assert {row for row in shown if row[1] != RTKLIB} == made


# ------------------------------------------------------------------------ 3: an untrained model is named

def _untrained_copy(path: Path) -> Path:
    """The shipped joint model as epoch 0 of a run from scratch (what an untrained run's best.pt exports)."""
    with np.load(MODEL_DIR / "lfgnss-default.npz") as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["metadata"]))
    meta.update(epoch=0, init_model=None)
    arrays["metadata"] = np.array(json.dumps(meta))
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **arrays)
    return path


def test_export_warns_of_an_untrained_checkpoint(runs, tmp_path, capsys):
    saved = torch.load(runs / "nodpc" / "last.pt", weights_only=False)
    torch.save({**saved, "epoch": 0}, tmp_path / "best.pt")                  # no epoch beat the untrained one
    assert export_main([str(tmp_path / "best.pt"), str(tmp_path / "e0.npz")]) == 0
    captured = capsys.readouterr()
    assert captured.out.startswith(f"{tmp_path / 'e0.npz'}: model of {tmp_path / 'best.pt'} (epoch 0)")
    assert captured.err == f"warning: {tmp_path / 'e0.npz'}: {UNTRAINED}, the randomly initialised network that " \
                           "no training epoch beat on validation; its noise can give positions far worse than the " \
                           "plain EKF's\n"
    assert export_main([str(runs / "nodpc" / "last.pt"), str(tmp_path / "e1.npz")]) == 0
    assert capsys.readouterr().err == ""


def test_the_benchmark_names_an_untrained_model_on_stderr_and_in_its_results(tmp_path, capsys, sample_toml):
    model = _untrained_copy(tmp_path / "runs" / "e0" / "model.npz")
    out = tmp_path / "out"
    assert bench_main(["my-drive", "--register", str(sample_toml("my-drive")), "--models", str(model), "--out",
                       str(out), "--no-plots"]) == 0
    err = capsys.readouterr().err.splitlines()
    assert err == [f"warning: {model} (rows 'LF-GNSS EKF (e0)', 'LF-GNSS EKF + RTS smoother (e0)', 'LF-GNSS FGO "
                   f"(e0)') {UNTRAINED}, the randomly initialised network that no training epoch beat on validation; "
                   "its noise can give positions far worse than the plain EKF's"]
    text = (out / "results.md").read_text()
    assert f"**Untrained models** (epoch 0 of a run from scratch, the random network: these rows' figures are no " \
           f"learned noise's): {model} (rows 'LF-GNSS EKF (e0)'" in text
    assert "| my-drive | LF-GNSS EKF (e0) | hk-tst-2019+berlin-pp+hk-tst-static-2020 (train), untrained (epoch 0) |" \
        in text


# ------------------------------------------------------------------------ 4: an ensemble's recipe before its seeds

def test_an_ensemble_of_other_features_names_both_sets_before_the_shared_seed(runs, tmp_path, capsys):
    full, nodpc = runs / "full" / "last.pt", runs / "nodpc" / "last.pt"
    err = _refused(export_main, [str(full), str(nodpc), str(tmp_path / "x.npz")], capsys)
    assert f"error: {nodpc}: feature_names differs from {full}'s (here: cn0, elevation, azimuth, residual; there: " \
           "cn0, elevation, azimuth, residual, dpc_gdop, dpc_pdop, dpc_hdop, dpc_vdop): an ensemble's members must " \
           "be one recipe" in err


def test_train_select_is_no_part_of_the_recipe_between_last_checkpoints_but_is_between_best_ones(runs, tmp_path,
                                                                                                  capsys):
    saved = torch.load(runs / "nodpc" / "last.pt", weights_only=False)
    other = {**saved, "config": {**saved["config"], "seed": 1,
                                 "train": {**saved["config"]["train"], "select": "last"}}}
    for name in ("last.pt", "best.pt"):
        (tmp_path / "s0").mkdir(exist_ok=True), (tmp_path / "s1").mkdir(exist_ok=True)
        torch.save(saved, tmp_path / "s0" / name)
        torch.save(other, tmp_path / "s1" / name)
    assert export_main([str(tmp_path / "s0" / "last.pt"), str(tmp_path / "s1" / "last.pt"),
                        str(tmp_path / "ens.npz")]) == 0
    assert len(load_model(tmp_path / "ens.npz").members) == 2
    capsys.readouterr()
    err = _refused(export_main, [str(tmp_path / "s0" / "best.pt"), str(tmp_path / "s1" / "best.pt"),
                                 str(tmp_path / "x.npz")], capsys)
    assert f"config train.select differs from {tmp_path / 's0' / 'best.pt'}'s (here: 'last'; there: 'val')" in err


# ------------------------------------------------------------------------ 5: training's unknown dataset

def test_an_unknown_dataset_tells_training_how_to_register_one(tmp_path, capsys):
    err = _refused(train_main, ["--config", CONFIG, "--out", str(tmp_path / "run"), "--no-progress",
                                *sets(TINY[1:] + ["data.datasets=['my-tsx']"])], capsys)
    assert "unknown dataset 'my-tsx'" in err and "--register FILE.toml" not in err
    assert "(register a dataset of your own first: --set 'data.register=[\"FILE.toml\"]' --set " \
           "'data.datasets=[\"ID\"]', or data.register = [\"FILE.toml\"] in the training config)" in err


# ------------------------------------------------------------------------ 6: no satellite slot

def test_a_sequence_of_no_satellite_slot_gets_empty_noise_and_the_ekf_coasts_as_the_plain_one():
    meas = lfgnss.load(SAMPLE_OBS, SAMPLE_NAV)
    truth = datasets.read_truth(SAMPLE_TRUTH, meas.time_gps_s, "smartloc")
    seq = lfgnss.build_sequence(meas, lfgnss.spp(meas), truth_ecef_m=truth).subset(slice(0, 40))
    T, N = seq.mask.shape
    per_slot = {f.name: getattr(seq, f.name)[:, :0] for f in dataclasses.fields(seq)
                if isinstance(getattr(seq, f.name), np.ndarray) and getattr(seq, f.name).shape[:2] == (T, N)}
    empty = dataclasses.replace(seq, **per_slot)
    model = load_model(MODEL_DIR / "lfgnss-default.npz")
    r, vc = model(empty)
    assert r.shape == vc.shape == (T, 0)
    learned, plain = estimators.create("ekf").solve(empty), estimators.create("plain-ekf").solve(empty)
    np.testing.assert_array_equal(learned.pos_ecef_m, plain.pos_ecef_m)
    np.testing.assert_array_equal(learned.status, plain.status)


def test_a_model_records_its_constellations_and_solve_names_those_it_never_saw():
    """Defect: a model trained on GPS only ran on GPS + BeiDou data without a word (44 m against 14 m 3D)."""
    from types import SimpleNamespace

    from learning.export import trained_systems
    from learning.train import data_span
    from lfgnss.solve import unseen_systems_note

    seq = lfgnss.process(SAMPLE_OBS, SAMPLE_NAV).subset(slice(0, 5))
    assert data_span("mine", "train", seq)["systems"] == "GR"
    g_only = SimpleNamespace(metadata={"data_spans": [{"systems": "G"}, {"systems": "G"}]})
    assert trained_systems(g_only.metadata) == "G"
    assert unseen_systems_note(g_only, ("G", "R")) == (
        "trained on G data only; this run's GLONASS satellites get R and v^c from a network that never saw that "
        "constellation (--systems G leaves them out)")
    assert unseen_systems_note(g_only, ("G",)) is None
    for older in ({"data_spans": [{"dataset": "x"}]}, {}):              # files of before session 50 say nothing
        assert trained_systems(older) is None and unseen_systems_note(SimpleNamespace(metadata=older), ("C",)) is None
    assert unseen_systems_note(None, ("G",)) is None                     # hand-set noise
    # a fine-tuned network keeps what its start learnt (review: fine-tuned on GR from a model of GC data, it was said
    # to have never seen BeiDou); a start that does not record its constellations (a bundled model) says nothing
    tuned = {"data_spans": [{"systems": "GR"}], "init_model": {"data_spans": [{"systems": "GC"}], "init_model": None}}
    assert trained_systems(tuned) == "GCR"                               # lfgnss order
    assert trained_systems({"data_spans": [{"systems": "GR"}], "init_model": {"data_spans": []}}) is None


def test_show_names_the_constellations_a_model_was_trained_on(runs, capsys):
    assert export_main(["--show", str(runs / "nodpc" / "model.npz")]) == 0
    shown = [line for line in capsys.readouterr().out.splitlines() if line.startswith("constellations trained on: ")]
    assert len(shown) == 1 and shown[0].removeprefix("constellations trained on: ") in ("G", "GC", "GR", "GCR", "GCER")


def test_resume_refuses_a_data_file_changed_since_the_run_started(sample_toml, tmp_path, capsys):
    """Review (session 50): --resume checked the dataset TOML's text, not the files it names."""
    from lfgnss.solve import SAMPLE_DIR

    truth = tmp_path / "gt.txt"
    shutil.copy(SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt", truth)
    toml = sample_toml("my-resume", truth=truth, splits=((0, 40), (40, 50), (50, 60)))
    out = tmp_path / "run"
    argv = ["--config", CONFIG, "--out", str(out), "--no-progress",
            *sets(TINY[1:] + [f"data.register=['{toml}']", "data.datasets=['my-resume']"])]
    assert train_main(argv) == 0
    capsys.readouterr()
    lines = truth.read_text().splitlines(keepends=True)
    truth.write_text("".join(lines[:-1]))                           # one truth row fewer
    err = _refused(train_main, ["--resume", "--out", str(out), "--set", "train.epochs=2", "--no-progress"], capsys)
    assert err == (f"python -m learning.train: error: {truth}: its content differs from when {out / 'last.pt'} was "
                   "started (dataset my-resume); a resumed run goes on with the data it was started with (log.csv and the best epoch would compare "
                   "two data sets): put the file back as it was, or start a new --out\n")
    truth.write_text("".join(lines))                                # put back: it resumes
    assert train_main(["--resume", "--out", str(out), "--set", "train.epochs=2", "--no-progress"]) == 0
