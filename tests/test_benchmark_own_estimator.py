"""An estimator of one's own in the benchmark (--plugin, --backend, ``run(extra=...)``) and the rows of one model
file (--models FILE), named after it, with their targets row and bars."""
import shutil
import sys
import textwrap

import numpy as np
import pytest

import estimators
import estimators.base
import lfgnss.benchmark as bench
from lfgnss import datasets
from lfgnss.benchmark import (MODEL_DIR, PLAIN, PLAIN_MAIN_FILTER, Method, main, methods, run, target_rows,
                              whole_test_split)
from lfgnss.errors import InputError
from lfgnss.metrics import METRIC_COLUMNS, accuracy_table
from lfgnss.sequence import DEFAULT_FEATURES

#: A plugin file: the equal-weight least squares moved 1 m along ECEF x, so that its row is its own.
PLUGIN = '''
import dataclasses

import estimators


@estimators.register("my-filter")
class MyFilter:
    """Least squares, moved 1 m; records the options it was made with."""

    name = "my-filter"
    made_with = []

    def __init__(self, noise=None, shift_m=1.0):
        MyFilter.made_with.append({"noise": noise, "shift_m": shift_m})
        self.shift_m = shift_m

    def solve(self, sequence):
        sol = estimators.create("wls").solve(sequence)
        return dataclasses.replace(sol, backend="my-filter", pos_ecef_m=sol.pos_ecef_m + [self.shift_m, 0.0, 0.0])
'''


@pytest.fixture(autouse=True)
def clean_registries(monkeypatch):
    """Leave no back end, dataset or plugin module registered behind."""
    estimators.backend_options("fgo")       # registers the lazy back end now: the copy below must hold it
    monkeypatch.setattr(estimators.base, "_REGISTRY", dict(estimators.base._REGISTRY))
    monkeypatch.setattr(datasets, "_REGISTRY", {}, raising=False)
    before = set(sys.modules)
    yield
    for name in set(sys.modules) - before:
        if name.startswith("lfgnss_plugin_") or name.startswith("my_filters_"):
            del sys.modules[name]


@pytest.fixture
def plugin(tmp_path):
    """``plugin(source, name)`` -> a .py file in ``tmp_path`` (default: PLUGIN as my_filter.py)."""
    def write(source: str = PLUGIN, name: str = "my_filter.py"):
        path = tmp_path / name
        path.write_text(textwrap.dedent(source))
        return path

    return write


@pytest.fixture
def model(tmp_path):
    """A training run's model file (the shipped joint model, copied)."""
    path = tmp_path / "model.npz"
    shutil.copy(MODEL_DIR / "lfgnss-default.npz", path)
    return path


def _table(text: str, section: str) -> dict[str, dict[str, str]]:
    """results.md's table under ``## section``: {method: {column: cell}}."""
    lines = [line for line in text.split(f"## {section}")[1].split("\n## ")[0].splitlines() if line.startswith("| ")]
    head = [c.strip() for c in lines[0].strip("| ").split(" | ")]
    rows = [dict(zip(head, (c.strip() for c in line.strip("| ").split(" | ")))) for line in lines[2:]]
    return {r["method"]: r for r in rows}


def _direct(dataset_id: str, backend: str) -> dict:
    """The figures of ``estimators.create(backend)`` run by hand on the dataset's test split."""
    span = whole_test_split(dataset_id, DEFAULT_FEATURES)
    sol = estimators.create(backend).solve(span)
    return accuracy_table(sol.pos_ecef_m, span.truth_ecef_m, sol.available, dataset=dataset_id, method=backend)


def test_an_extra_row_has_the_figures_of_its_estimator_run_by_hand(tmp_path, plugin, sample_toml):
    bench.load_plugin(str(plugin()))
    datasets.register_toml(sample_toml("my-drive"))
    rows, _ = run(["my-drive"], model_dir=tmp_path / "no-models", plots=False, extra=[Method("mine", "my-filter")])
    assert [r["method"] for r in rows][-1] == "mine"                        # after the built-in rows
    mine = rows[-1]
    direct = _direct("my-drive", "my-filter")
    assert {k: mine[k] for k in METRIC_COLUMNS} == {k: direct[k] for k in METRIC_COLUMNS}
    plain = next(r for r in rows if r["method"] == "least squares (equal weight)")
    assert mine["rmse_3d_m"] != plain["rmse_3d_m"]                          # really the plugin's estimator
    assert mine["trained_on"] == "-" and mine["n_labelled"] > 0


def test_the_command_line_runs_a_plugins_backend_as_a_row(tmp_path, plugin, sample_toml, model, capsys):
    out = tmp_path / "out"
    assert main(["my-drive", "--register", str(sample_toml("my-drive")), "--models", str(model), "--plugin",
                 str(plugin()), "--backend", "my-filter", "--out", str(out), "--no-plots"]) == 0
    captured = capsys.readouterr()
    assert captured.err == "" and "my-filter" in captured.out
    made = sys.modules["lfgnss_plugin_my_filter"].MyFilter.made_with
    assert made and all(m == {"noise": None, "shift_m": 1.0} for m in made)     # no options, no model: its defaults
    text = (out / "results.md").read_text()
    row = _table(text, "All labelled test epochs")["my-filter"]
    direct = _direct("my-drive", "my-filter")
    assert row["3D RMSE [m]"] == f"{direct['rmse_3d_m']:.2f}" and row["2D RMSE [m]"] == f"{direct['rmse_2d_m']:.2f}"
    assert row["solved"] == str(direct["n_solved"]) and row["trained_on"] == "-"
    assert "my-filter" not in _table(text, "Against the targets")           # not an LF-GNSS row
    assert "--plugin" in text and "--backend my-filter" in text              # the recorded command


def test_a_plugin_module_is_imported_by_its_dotted_name(tmp_path, monkeypatch):
    (tmp_path / "my_filters_pkg").mkdir()
    (tmp_path / "my_filters_pkg" / "__init__.py").write_text("")
    (tmp_path / "my_filters_pkg" / "kalman.py").write_text(PLUGIN.replace('"my-filter"', '"dotted-filter"'))
    monkeypatch.syspath_prepend(str(tmp_path))
    module = bench.load_plugin("my_filters_pkg.kalman")
    assert module.__name__ == "my_filters_pkg.kalman" and "dotted-filter" in estimators.available()
    assert bench.own_rows([], ["dotted-filter"]) == [Method("dotted-filter", "dotted-filter")]


BROKEN = "import estimators\nraise RuntimeError('no licence\\nfor this filter')\n"
EXITS = "import sys\nsys.exit('usage: my_filter.py FILE')\n"
NEEDS_AN_ARGUMENT = '''
import estimators

@estimators.register("needs-arg")
class NeedsArg:
    def __init__(self, weights):
        self.weights = weights
'''
CLASHES = PLUGIN.replace('"my-filter"', '"plain EKF (C/N0 noise, gate)"')


@pytest.mark.parametrize("source, args, message", [
    (None, ["--backend", "nope"], "nope: unknown back end (--backend); available: ekf, fgo, plain-ekf, wls, "
                                  "wls-weighted; one of your own: give the module or .py file whose import registers "
                                  "it (@estimators.register('nope')) as --plugin"),
    (None, ["--plugin", "{tmp}/gone.py"], "{tmp}/gone.py: no such .py file (--plugin)"),
    (None, ["--plugin", "no_such_module_of_mine"], "no_such_module_of_mine: cannot import (--plugin): "
                                                   "ModuleNotFoundError: No module named 'no_such_module_of_mine'"),
    (BROKEN, ["--plugin", "{plugin}"], "{plugin}: cannot import (--plugin): RuntimeError: no licence for this filter"),
    (EXITS, ["--plugin", "{plugin}"], "{plugin}: cannot import (--plugin): SystemExit: usage: my_filter.py FILE"),
    (NEEDS_AN_ARGUMENT, ["--plugin", "{plugin}", "--backend", "needs-arg"],
     "needs-arg: estimators.create('needs-arg') failed (--backend): TypeError: NeedsArg.__init__() missing 1 "
     "required positional argument: 'weights'"),
    (CLASHES, ["--plugin", "{plugin}", "--backend", PLAIN],
     f"{PLAIN}: the benchmark has a row of that name already (built in, or given twice); give the estimator of your "
     "own another name"),
    (PLUGIN, ["--plugin", "{plugin}", "--backend", "my-filter", "--backend", "my-filter"],
     "my-filter: the benchmark has a row of that name already (built in, or given twice); give the estimator of your "
     "own another name"),
], ids=["unknown backend", "no such file", "no such module", "raises", "exits", "cannot be made", "row name taken",
        "given twice"])
def test_a_bad_plugin_or_backend_is_one_line_before_any_work(source, args, message, tmp_path, plugin, sample_toml,
                                                             monkeypatch, capsys):
    path = plugin(source) if source else None
    monkeypatch.setattr(bench, "run", lambda *a, **k: pytest.fail("ran before checking --plugin and --backend"))
    argv = [a.format(tmp=tmp_path, plugin=path) for a in args]
    out = tmp_path / "out"
    assert main(["my-drive", "--register", str(sample_toml("my-drive")), *argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == "error: " + message.format(tmp=tmp_path, plugin=path) + "\n"
    assert not out.exists()


def test_a_backend_that_raises_costs_its_row_only(tmp_path, plugin, sample_toml, model, capsys):
    path = plugin(PLUGIN.replace('"my-filter"', '"bad-filter"').replace(
        "        sol = estimators", "        raise ValueError('operands could not be broadcast')\n        sol = estimators"))
    out = tmp_path / "out"
    assert main(["my-drive", "--register", str(sample_toml("my-drive")), "--models", str(model), "--plugin",
                 str(path), "--backend", "bad-filter", "--out", str(out), "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err == ("error: my-drive: row 'bad-filter' left out: its estimator raised ValueError: operands could not "
                   "be broadcast\n")
    text = (out / "results.md").read_text()
    assert "**Rows left out** (the estimator of one's own raised; the tables leave that row out on that dataset): " \
           "my-drive: row 'bad-filter' left out" in text
    rows = _table(text, "All labelled test epochs")
    assert "bad-filter" not in rows and {PLAIN, f"LF-GNSS EKF ({model.parent.name})"} <= set(rows)
    with pytest.raises(ValueError, match="broadcast"):                     # run() without left_out: raised
        run(["my-drive"], model_dir=tmp_path / "no-models", plots=False, extra=[Method("bad", "bad-filter")])


def test_a_solution_that_is_not_one_is_left_out_naming_what_it_is(tmp_path, plugin, sample_toml):
    bench.load_plugin(str(plugin(PLUGIN.replace('"my-filter"', '"dict-filter"').replace(
        "        return dataclasses.replace(", "        return {}\n        return dataclasses.replace("))))
    datasets.register_toml(sample_toml("my-drive"))
    left_out: list[str] = []
    rows, _ = run(["my-drive"], model_dir=tmp_path / "no-models", plots=False,
                  extra=[Method("dict", "dict-filter")], left_out=left_out)
    assert left_out == ["my-drive: row 'dict' left out: its estimator raised TypeError: solve returned dict, not an "
                        "estimators.Solution"]
    assert "dict" not in {r["method"] for r in rows} and PLAIN in {r["method"] for r in rows}


def test_extra_rows_come_last_and_may_not_take_a_rows_name(tmp_path):
    mine = Method("mine", "wls")
    assert [m.name for m in methods(tmp_path, "berlin-pp", [mine])][-1] == "mine"
    for taken in (PLAIN, "RTKLIB rnx2rtkp", "RTKLIB"):
        with pytest.raises(ValueError, match="has a row of that name already"):
            methods(tmp_path, "berlin-pp", [Method(taken, "wls")])
    with pytest.raises(ValueError, match="mine: the benchmark has a row of that name already"):
        methods(tmp_path, "berlin-pp", [mine, Method("mine", "wls-weighted")])
    with pytest.raises(TypeError, match="expected lfgnss.benchmark.Method objects, got str"):
        methods(tmp_path, "berlin-pp", ["wls"])


def test_a_model_files_rows_carry_its_name_and_the_bundled_rows_keep_theirs(model):
    names = [m.name for m in methods(model, "berlin-pp")]
    label = f"({model.parent.name})"                # a run's model.npz: named by its folder, as lfgnss.solve names it
    assert names[-4:] == [f"{PLAIN_MAIN_FILTER} {label}", f"LF-GNSS EKF {label}",
                          f"LF-GNSS EKF + RTS smoother {label}", f"LF-GNSS FGO {label}"]
    bundled = [m.name for m in methods(MODEL_DIR, "berlin-pp")]
    assert {PLAIN_MAIN_FILTER, "LF-GNSS EKF", "LF-GNSS EKF + RTS smoother", "LF-GNSS FGO"} <= set(bundled)
    assert not any(".npz)" in name for name in bundled)                     # docs/results.md keeps its names


def _row(method, d3, d2):
    return {"dataset": "hk-tst-2019", "method": method, "trained_on": "-", "rmse_3d_m": d3, "rmse_2d_m": d2}


def test_a_model_files_rows_get_their_targets_row_and_bars():
    table = [_row(PLAIN, 30.0, 20.0), _row(f"{PLAIN_MAIN_FILTER} (FGO.npz)", 20.0, 10.0),
             _row("LF-GNSS EKF (FGO.npz)", 15.0, 9.0), _row("LF-GNSS FGO (FGO.npz)", 12.0, 8.0),
             _row("plain EKF + RTS smoother", 11.0, 7.0), _row("LF-GNSS EKF + RTS smoother (FGO.npz)", 10.0, 6.0)]
    rows = {r["method"]: r for r in target_rows(table, [])}
    assert set(rows) == {"LF-GNSS EKF (FGO.npz)", "LF-GNSS FGO (FGO.npz)", "LF-GNSS EKF + RTS smoother (FGO.npz)"}
    ekf = rows["LF-GNSS EKF (FGO.npz)"]
    assert ekf["3D vs plain EKF"] == "15.00 vs 20.00 (yes)"                 # the plain EKF in its model's filter
    assert ekf["3D vs yardstick"] == "15.00 vs 14.00 (no)"                  # an EKF, whatever the file is called
    assert ekf["3D vs target"] == "15.00 vs 10.00 (no)"
    assert rows["LF-GNSS FGO (FGO.npz)"]["3D vs yardstick"] == "12.00 vs 12.20 (yes)"
    assert rows["LF-GNSS FGO (FGO.npz)"]["3D vs plain EKF"] == "12.00 vs 30.00 (yes)"
    assert rows["LF-GNSS EKF + RTS smoother (FGO.npz)"]["3D vs plain EKF"] == "10.00 vs 11.00 (yes)"


def test_a_model_files_rows_reach_the_targets_table_and_the_figures(tmp_path, sample_toml, model, monkeypatch):
    import lfgnss.outputs

    labels = []
    monkeypatch.setattr(lfgnss.outputs, "plot_solution", lambda *a, label=None, **k: labels.append(label))
    datasets.register_toml(sample_toml("my-drive"))
    rows, rtk = run(["my-drive"], model_dir=model, out_dir=tmp_path, plots=True)
    label = f"({model.parent.name})"
    assert labels == [f"LF-GNSS EKF {label}"]                               # the figures' main solution
    figures = {r["method"]: r for r in rows}
    targets = {r["method"]: r for r in target_rows(rows, rtk)}
    assert {f"LF-GNSS EKF {label}", f"LF-GNSS FGO {label}"} <= set(targets)
    bar = figures[f"{PLAIN_MAIN_FILTER} {label}"]["rmse_3d_m"]
    assert targets[f"LF-GNSS EKF {label}"]["3D vs plain EKF"].split(" (")[0].endswith(f"vs {bar:.2f}")
    assert np.isfinite(bar) and bar != figures[PLAIN]["rmse_3d_m"]


def test_the_help_names_the_options_and_the_labels(monkeypatch, capsys):
    monkeypatch.setenv("COLUMNS", "1000")
    with pytest.raises(SystemExit):
        main(["--help"])
    shown = capsys.readouterr().out
    assert "--plugin MODULE_OR_FILE" in shown and "--backend NAME" in shown
    assert "@estimators.register(\"NAME\")" in shown and "estimators.create(NAME)" in shown
    assert "The targets table reads only LF-GNSS rows" in shown
    assert "LF-GNSS EKF (x), LF-GNSS EKF + RTS smoother (x), LF-GNSS FGO (x) for a run's runs/x/model.npz" in shown


def test_rows_of_ones_own_never_go_into_the_committed_results(tmp_path, monkeypatch):
    import argparse

    import lfgnss.paths
    from lfgnss.benchmark import DEFAULT_DATASETS, _refuse_partial_docs

    monkeypatch.setattr(lfgnss.paths, "REPO_DIR", tmp_path)
    args = argparse.Namespace(out=tmp_path / "docs", register=[], models=MODEL_DIR, plugin=["my_filter.py"],
                              backend=["my-filter"])
    with pytest.raises(InputError, match=r"this run \(--plugin my_filter.py; --backend my-filter\) would replace"):
        _refuse_partial_docs(args, list(DEFAULT_DATASETS))


@pytest.mark.parametrize("name", ["ekf", "fgo"])
def test_a_plugin_that_replaces_a_built_in_back_end_is_refused(name, tmp_path, plugin, sample_toml, monkeypatch,
                                                               capsys):
    """Else every built-in row of that back end (LF-GNSS EKF, FGO ...) would run the plugin's code under its name."""
    path = plugin(PLUGIN.replace('"my-filter"', f'"{name}"'))
    monkeypatch.setattr(bench, "run", lambda *a, **k: pytest.fail("ran a plugin that replaced a built-in back end"))
    assert main(["my-drive", "--register", str(sample_toml("my-drive")), "--plugin", str(path),
                 "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[-1] == (f"error: {path}: replaces the built-in back end {name!r} (--plugin): register your estimator "
                       "under a name of its own")
    assert not (tmp_path / "out").exists()


def test_a_plugin_imports_the_modules_beside_it_and_a_row_name_is_one_table_cell(tmp_path, plugin, sample_toml,
                                                                                 monkeypatch, capsys):
    (tmp_path / "my_filters_helper.py").write_text("SHIFT_M = 2.0\n")
    path = plugin("import my_filters_helper\n" + PLUGIN.replace("shift_m=1.0", "shift_m=my_filters_helper.SHIFT_M"))
    bench.load_plugin(str(path))
    assert estimators.create("my-filter").shift_m == 2.0
    monkeypatch.setattr(bench, "run", lambda *a, **k: pytest.fail("ran with a row name that breaks the tables"))
    assert main(["my-drive", "--register", str(sample_toml("my-drive")), "--backend", "a|b",
                 "--out", str(tmp_path / "out")]) == 2
    assert "a|b: a row name (--backend) must not be blank or hold '|'" in capsys.readouterr().err
