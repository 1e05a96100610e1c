"""``python -m lfgnss.benchmark``: every estimator side by side on the test splits of shared/BENCHMARK.md.

For each dataset: RTKLIB ``rnx2rtkp`` (when installed), equal-weight and weighted least squares, the
plain EKF, the LF-GNSS EKF and factor graph with the shipped (joint) model, the three ablation models
(w/o DPC, w/o HEM, w/o both) in the EKF, and the EKF and factor graph with the dataset's own model
(``lfgnss-<dataset id>.npz``, trained on that dataset's train split only) where there is one. The plain and
LF-GNSS EKFs also run with the RTS smoother (``estimators.smoother``, post-processing) as rows of their own. Where
the dataset's own model was trained in a filter other than the default one (process noise, Doppler weights, Huber),
the plain EKF runs in that filter too, so that the learned noise's share of the gain shows.
Writes a Markdown results table (all test epochs, and the epochs RTKLIB solved, and each learned row against the
targets and yardstick of BENCHMARK.md), CDF and track PNGs per dataset, into ``--out`` (default ``lfgnss-benchmark/``
in the current folder; ``--out docs`` from the repository root regenerates its committed docs/results.md, and
takes only the whole default run: a dataset subset, a dataset of one's own or other models are refused there).

results.md records the command, the code (lfgnss version, git commit) and the SHA-256 of each model file read, and
names a model trained or selected on epochs of a test split it scores (``models_that_saw_test_epochs``; a warning too).
An ``rnx2rtkp`` that fails, hangs or writes an unreadable solution costs the RTKLIB row only (a warning says why).

``--models`` names another folder of such files, matched to the rows by name as the bundled ones are
(``lfgnss-default.npz``, the ablations' ``lfgnss-no_*.npz``, ``lfgnss-<dataset id>.npz``), or one model file (a
training run's ``model.npz``), which then takes the shipped model's rows on every dataset, named after the file as
``lfgnss.solve`` names its outputs (a run's ``runs/a/model.npz`` by its folder) so that they are told apart from the
shipped model's: ``LF-GNSS EKF (a)``, ``LF-GNSS EKF + RTS smoother (a)``, ``LF-GNSS FGO (a)`` and, where it was
trained in a filter of its own, ``plain EKF in the LF-GNSS EKF's filter (a)`` (``file_label``); they keep their
targets row and bars. ``--models`` is given once (twice is an option error). A model that holds no training (epoch 0
of a run from scratch) is named in a warning and in results.md, and its rows' ``trained_on`` says so. ``--register
my-drive.toml`` adds a user's dataset (``lfgnss.datasets.register_toml``) to the run.

An estimator of one's own runs as rows too: ``--plugin my_filter.py`` (a ``.py`` file, or a module's dotted name)
is imported first, and its ``@estimators.register("my-filter")`` class is then ``--backend my-filter``: a row named
``my-filter`` on every dataset, made with ``estimators.create("my-filter")`` (no options: no model either), after
the built-in rows. From Python, ``run(ids, extra=[Method("mine", "my-filter", options={...})])`` (and
``methods(..., extra=...)``) adds such rows; a name that a built-in row has is a ValueError. On the command line an
error in that estimator's own code costs its row on that dataset (``error: ...`` at the end, exit status 2), not
the run; ``run`` raises it unless given a ``left_out`` list. The targets table reads only rows whose name starts
with ``LF-GNSS``.
"""
from __future__ import annotations

import argparse
import importlib
import os
import re
import shlex
import sys
import tempfile
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Collection, Iterator

import numpy as np

from . import datasets
from .errors import (INPUT_ERRORS, InputError, cannot_write, input_line, one_line, path_option, run_command,
                     shortened, stdout_gone)
from .help_text import PlainHelp
from .metrics import METRIC_COLUMNS, accuracy_table, format_markdown, format_text, markdown_table
from .paths import bundled_data_dir, make_output_folder, write_output
from .sequence import Sequence

MODEL_DIR = bundled_data_dir() / "model"
ABLATIONS = {"LF-GNSS EKF w/o DPC": "lfgnss-no_dpc.npz", "LF-GNSS EKF w/o HEM": "lfgnss-no_hem.npz",
             "LF-GNSS EKF w/o both": "lfgnss-no_dpc_no_hem.npz"}
DEFAULT_MODEL = "lfgnss-default.npz"
#: Files of the bundled model folder that are on purpose no benchmark row (the start of the hk fine-tuning).
BUNDLED_NOT_ROWS = frozenset({"lfgnss-transfer-base.npz"})
DEFAULT_DATASETS = ("hk-tst-2019", "berlin-pp", "hk-tst-static-2020")
#: Where a run writes without ``--out`` (in the current folder); ``--out docs`` writes the committed results.
DEFAULT_OUT = "lfgnss-benchmark"


#: Targets for the learned EKF and the independent yardstick's figures (3D, 2D RMSE [m], test splits), quoted
#: from shared/BENCHMARK.md: the bar the "against the targets" table measures our rows with.
TARGETS = {"hk-tst-2019": (10.0, 3.5), "berlin-pp": (12.0, 6.0), "hk-tst-static-2020": (1.5, 1.0)}
YARDSTICK_EKF = {"hk-tst-2019": (14.0, 7.9), "berlin-pp": (27.0, 13.2), "hk-tst-static-2020": (2.9, 2.4)}
YARDSTICK_GRAPH = {"hk-tst-2019": (12.2, 8.5), "berlin-pp": (13.8, 8.0), "hk-tst-static-2020": (2.7, 2.3)}
PLAIN = "plain EKF (C/N0 noise, gate)"
PLAIN_RTS = "plain EKF + RTS smoother"
PLAIN_OWN_FILTER = "plain EKF in the per-dataset model's filter"
PLAIN_MAIN_FILTER = "plain EKF in the LF-GNSS EKF's filter"
OWN_EKF = "LF-GNSS EKF, per-dataset model"
MAIN_EKF = "LF-GNSS EKF"
MAIN_FGO = "LF-GNSS FGO"
RTS = " + RTS smoother"
RTKLIB = "RTKLIB rnx2rtkp"
#: Splits ``--warm-up`` may start the filters at (it must come before the test split).
WARM_UP = ("train", "val")


@dataclass
class Method:
    """One row of the benchmark: its name and ``estimators.create(backend, **options)``, ``model`` loaded as ``noise``.

    Rows of one's own go to ``run(..., extra=[Method("mine", "my-filter")])`` after ``@estimators.register``.
    """

    name: str
    backend: str
    model: Path | None = None
    options: dict | None = None

    def create(self):
        """The estimator, with its model loaded."""
        import estimators

        options = dict(self.options or {})
        if self.model is not None:
            from learning.export import load_model

            options["noise"] = load_model(self.model)
        return estimators.create(self.backend, **options)


def file_label(model_dir: Path) -> str:
    """What the shipped model's row names get from ``--models``: `` (NAME)`` for one model file, named as
    ``lfgnss.solve`` names its outputs (``mine.npz``: ``mine``; a training run's ``runs/a/model.npz``: ``a``), else
    nothing."""
    from .solve import model_tag

    return f" ({model_tag(Path(model_dir))})" if Path(model_dir).is_file() else ""


def split_label(name: str) -> tuple[str, str]:
    """A row name as (built-in name, ``file_label``): ``LF-GNSS FGO (m)`` -> (``LF-GNSS FGO``, `` (m)``)."""
    for base in (MAIN_EKF, MAIN_EKF + RTS, MAIN_FGO, PLAIN_MAIN_FILTER):
        if name.startswith(base + " (") and name.endswith(")"):
            return base, name[len(base):]
    return name, ""


def methods(model_dir: Path = MODEL_DIR, dataset_id: str | None = None,
            extra: list[Method] | tuple[Method, ...] = ()) -> list[Method]:
    """Baselines always; learned rows where their model file exists (per-dataset ones for ``dataset_id``); ``extra``.

    A model trained in a filter other than the default also brings the plain EKF in that filter (``PLAIN_OWN_FILTER``
    for the per-dataset model, ``PLAIN_MAIN_FILTER`` for the shipped one; its file is read here for the settings).
    ``model_dir`` is a folder of ``lfgnss-*.npz`` files, or one model file that takes the rows of the shipped (joint)
    model on every dataset, their names ending in its ``file_label``. ``extra``: rows of one's own, last; ValueError
    for one named as another row.
    """
    from learning.export import load_model

    def plain_in_its_filter(model: Path, name: str) -> list[Method]:
        """The hand-set noise in the learned rows' filter: what the learning adds (none in the default filter)."""
        config = own_filter(load_model(model))
        return [] if config is None else [Method(name, "plain-ekf", options={"config": config})]

    rows = [Method("least squares (equal weight)", "wls"), Method("least squares (C/N0-weighted)", "wls-weighted"),
            Method(PLAIN, "plain-ekf"), Method(PLAIN_RTS, "plain-ekf", options={"smooth": True})]
    model_dir = Path(model_dir)
    own = model_dir / f"lfgnss-{dataset_id}.npz"
    has_own = dataset_id is not None and model_dir.is_dir() and own.exists()
    if has_own:
        rows += plain_in_its_filter(own, PLAIN_OWN_FILTER)
    default, label = (model_dir if model_dir.is_file() else model_dir / DEFAULT_MODEL), file_label(model_dir)
    if default.is_file():
        rows += plain_in_its_filter(default, PLAIN_MAIN_FILTER + label)
        rows += [Method(MAIN_EKF + label, "ekf", default),
                 Method(MAIN_EKF + RTS + label, "ekf", default, {"smooth": True}),
                 Method(MAIN_FGO + label, "fgo", default)]
    if model_dir.is_dir():
        rows += [Method(name, "ekf", model_dir / f) for name, f in ABLATIONS.items() if (model_dir / f).exists()]
    if has_own:
        rows += [Method(OWN_EKF, "ekf", own),
                 Method(f"LF-GNSS EKF{RTS}, per-dataset model", "ekf", own, {"smooth": True}),
                 Method("LF-GNSS FGO, per-dataset model", "fgo", own)]
    return rows + _checked_extra(rows, extra)


def _checked_extra(rows: list[Method], extra: list[Method] | tuple[Method, ...]) -> list[Method]:
    """``extra`` as a list; TypeError for what is no Method, ValueError for a name the table has already."""
    taken = {m.name for m in rows} | {RTKLIB, "RTKLIB"}      # "RTKLIB": the figures' name for its row
    for m in extra:
        if not isinstance(m, Method):
            raise TypeError(f"extra rows: expected lfgnss.benchmark.Method objects, got {type(m).__name__}")
        if m.name in taken:
            raise ValueError(f"{m.name}: the benchmark has a row of that name already (built in, or given twice); "
                             "give the estimator of your own another name")
        taken.add(m.name)
    return list(extra)


def own_filter(noise):
    """The ``EkfConfig`` a learned noise model was trained in (``estimators.ekf.config_of``); None if the default one."""
    from estimators.ekf import config_of
    from estimators.models import EkfConfig

    config = config_of(noise)
    return None if config == EkfConfig() else config


def expected_model_names(dataset_ids) -> list[str]:
    """The file names a models folder is read for: the joint model, the ablations and one per dataset id."""
    return [DEFAULT_MODEL, *ABLATIONS.values(), *(f"lfgnss-{d}.npz" for d in dataset_ids)]


def check_models(models: Path, dataset_ids: list[str]) -> list[str]:
    """Warnings about ``--models`` (unused ``.npz`` files of a folder); InputError if it gives these datasets no model.

    Every model file the run will use is loaded once here, so a bad one stops the run before it starts.
    """
    from learning.export import load_model

    models = Path(models)
    if not models.exists():
        raise InputError(models, "no such model file or folder (--models)")
    if models.is_file():
        used = [models]
    else:
        used = sorted({m.model for d in dataset_ids for m in methods(models, d) if m.model is not None})
    for path in used:
        load_model(path)
    if models.is_file():
        return []
    known = set(expected_model_names(datasets.registered()))
    if models.resolve() == MODEL_DIR.resolve():
        known |= BUNDLED_NOT_ROWS
    unused = sorted(p.name for p in models.glob("*.npz") if p not in used and p.name not in known)
    expected = (f"expected {DEFAULT_MODEL} (every dataset), {', '.join(ABLATIONS.values())} (ablations) or "
                f"lfgnss-<dataset id>.npz ({', '.join(f'lfgnss-{d}.npz' for d in dataset_ids)})")
    hint = f"; to use one model file for every dataset, give the file itself: --models {models / unused[0]}" \
        if unused else ""
    if not used:
        found = f"; it holds only {', '.join(unused)}" if unused else ""
        raise InputError(models, f"no model file for {', '.join(dataset_ids)} in this folder: {expected}{found}{hint}")
    return [f"{models}: not using {', '.join(unused)}: {expected}{hint}"] if unused else []


def load_plugin(spec: str) -> ModuleType:
    """Import a ``--plugin``: a ``.py`` file by its path (any name with a folder in it too), else a dotted module name.

    Its import is to register estimators (``@estimators.register``); InputError naming ``spec`` and the exception
    if it fails, the plugin's own code included.
    """
    is_file = spec.endswith(".py") or os.sep in spec or bool(os.altsep and os.altsep in spec)
    if is_file and not Path(spec).is_file():
        raise InputError(spec, "no such .py file (--plugin)")
    try:
        return _import_file(Path(spec)) if is_file else importlib.import_module(spec)
    except (Exception, SystemExit) as err:  # whatever the plugin's code raises: one line, no traceback
        raise InputError(spec, f"cannot import (--plugin): {type(err).__name__}: {one_line(err)}") from None


def _import_file(path: Path) -> ModuleType:
    """The module of a ``.py`` file, imported as ``lfgnss_plugin_<its stem>``."""
    import importlib.util

    name = "lfgnss_plugin_" + re.sub(r"\W", "_", path.stem)
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None:
        raise ImportError("not a Python file (a .py file, or a module's dotted name)")
    module = importlib.util.module_from_spec(spec)
    folder = str(path.resolve().parent)
    if folder not in sys.path:          # as running the file would: modules beside it import
        sys.path.insert(0, folder)
    sys.modules[name] = module          # as an import does: dataclasses and pickle look the module up there
    try:
        spec.loader.exec_module(module)
    except BaseException:
        sys.modules.pop(name, None)
        raise
    return module


def own_rows(plugins: list[str], backends: list[str]) -> list[Method]:
    """The ``--backend`` rows, after importing the ``--plugin``s; InputError for a back end unknown or not made."""
    import estimators
    from estimators.base import factories

    for spec in dict.fromkeys(plugins):
        before = factories()
        load_plugin(spec)
        taken = [n for n, f in before.items() if factories()[n] is not f
                 and not (isinstance(f, str) and getattr(factories()[n], "__module__", None) == f)]
        if taken:                       # else every built-in row of that back end would run the plugin's code
            raise InputError(spec, f"replaces the built-in back end {taken[0]!r} (--plugin): register your "
                                   "estimator under a name of its own")
    for name in backends:
        if not name.strip() or any(c in name for c in "|\r\n"):
            raise InputError(name, "a row name (--backend) must not be blank or hold '|' or a line break: it is a "
                                   "cell of the results tables")
        if name not in estimators.available():
            raise InputError(name, f"unknown back end (--backend); available: {', '.join(estimators.available())}; "
                                   f"one of your own: give the module or .py file whose import registers it "
                                   f"(@estimators.register({name!r})) as --plugin")
    rows = [Method(name, name) for name in backends]
    for m in rows:                      # made once now, so that one that cannot be made costs no run
        try:
            m.create()
        except Exception as err:
            raise InputError(m.name, f"estimators.create({m.name!r}) failed (--backend): {type(err).__name__}: "
                                     f"{one_line(err)}") from None
    return rows


def resolve_datasets(ids: list[str], toml_files: list[str | Path] = (),
                     need_splits: tuple[str, ...] = ("test",)) -> list[str]:
    """Register the TOML datasets, then the ids to run: those given plus the registered ones (default: the three).

    Raises KeyError (listing the known ids) for an unknown id, and InputError for an unusable TOML file or one
    without the splits the run scores (``need_splits``: the test split, and the ``--warm-up`` one).
    """
    registered = [datasets.register_toml(path, need_splits=need_splits).id for path in toml_files]
    out = list(dict.fromkeys([*ids, *registered])) or list(DEFAULT_DATASETS)
    for dataset_id in out:
        datasets.get(dataset_id, hint="a dataset of your own: --register FILE.toml")
    return out


def _features_for(plugins) -> tuple[str, ...]:
    """The default features plus any further ones the estimators' models read, so one sequence serves every row."""
    from .sequence import DEFAULT_FEATURES

    names = list(DEFAULT_FEATURES)
    for estimator in plugins:
        names += [n for n in getattr(getattr(estimator, "noise", None), "feature_names", ()) if n not in names]
    return tuple(names)


def rtklib_solution(spec, workdir: Path, systems: tuple[str, ...] | None = None):
    """RTKLIB's SPP solution of the dataset's obs file with the benchmark's settings and its run time [s], or (None, None).

    Constellations: the dataset's ``systems``, else ``systems`` (those its sequence has: the other rows' satellites),
    else GPS.

    None without ``rnx2rtkp``, or (with a line on stderr) for a dataset of several obs files.
    """
    from .rtklib import RtklibError, rtklib_available, spp_solution

    if not rtklib_available():
        return None, None
    if len(spec.obs) > 1:     # rnx2rtkp would take a second obs file for a base station's
        print(f"{spec.id}: RTKLIB row left out: the dataset has {len(spec.obs)} obs files", file=sys.stderr)
        return None, None
    try:
        return spp_solution(spec.obs[0], list(spec.nav), workdir / f"{spec.id}.pos",
                            systems=spec.systems or systems or ("G",))
    except (RtklibError, ValueError) as err:  # rnx2rtkp failed, hung or wrote an unreadable .pos: an optional row
        # cut: an rnx2rtkp command line names every file of the dataset
        print(f"warning: {spec.id}: RTKLIB row left out: {shortened(one_line(err), 300)}", file=sys.stderr)
        return None, None


def _rtklib_on(seq, spec, workdir: Path):
    """RTKLIB's solution matched to the sequence's epochs (NaN where it gave none), and its run time."""
    from .outputs import align_to

    sol, seconds = rtklib_solution(spec, workdir, tuple(seq.systems))
    return (None, None) if sol is None else (align_to(seq.time_gps_s, sol), seconds)


def whole_test_split(dataset_id: str, feature_names: tuple[str, ...]) -> Sequence:
    """The test split as one Sequence from its first to its last labelled epoch (InputError if it has none).

    Epochs inside it without truth are solved but not scored (as in ``load_split``'s pieces).
    """
    return scored_span(dataset_id, feature_names)[0]


def scored_span(dataset_id: str, feature_names: tuple[str, ...], warm_up: str | None = None) -> tuple[Sequence, int]:
    """The Sequence the estimators solve and how many of its first epochs precede the test split (unscored).

    Without ``warm_up`` it is ``whole_test_split``'s span. With a split name (``WARM_UP``) it starts at that split's
    first labelled epoch, which must come before the test split: the filters then enter the test split warm, as a
    receiver that has been running does. Only observations of the warm-up epochs are used, never their truth.
    """
    spec = datasets.get(dataset_id)
    seq = datasets.build(dataset_id, feature_names=feature_names)
    idx = np.flatnonzero(datasets.split_index(seq, spec, "test"))
    where = spec.source or spec.truth            # a TOML's [splits], else the truth that labels no epoch there
    if idx.size == 0:
        raise InputError(where, datasets.empty_split_words(seq, spec, "test"))
    start = idx[0]
    if warm_up is not None:
        warm = np.flatnonzero(datasets.split_index(seq, spec, warm_up))
        if warm.size == 0:
            raise InputError(where, f"--warm-up {warm_up}: {datasets.empty_split_words(seq, spec, warm_up)}")
        if warm[0] >= idx[0]:
            raise InputError(where, f"dataset {dataset_id}: --warm-up {warm_up} needs labelled epochs of that "
                                    f"split before the test split (splits {spec.splits})")
        start = warm[0]
    name = f"{dataset_id}/test" if warm_up is None else f"{dataset_id}/{warm_up}+test"
    return seq.subset(slice(start, idx[-1] + 1), name=name), int(idx[0] - start)


def run(dataset_ids: list[str], *, model_dir: Path = MODEL_DIR, out_dir: Path | None = None,
        plots: bool = True, unwritten: list[str] | None = None, warm_up: str | None = None,
        failed: list[str] | None = None, extra: list[Method] | tuple[Method, ...] = (),
        left_out: list[str] | None = None, leaked: list[str] | None = None,
        untrained: list[str] | None = None) -> tuple[list[dict], list[dict]]:
    """Rows over all test epochs and rows over RTKLIB's solved test epochs, for each dataset.

    ``unwritten``: a list that collects ``FILE: cannot write (reason)`` for figures that could not be written (the
    run goes on); without it such an OSError is raised. ``warm_up``: a split of ``WARM_UP`` the estimators start at
    (``scored_span``); the rows still score the test split only. ``failed``: a list that collects ``ID: reason`` for a
    dataset whose files turn out bad (the other datasets still run); without it that error is raised. ``extra``: rows
    of one's own (``Method``), after the built-in ones on every dataset; a name taken is a ValueError before any
    work. ``left_out``: a list that collects ``ID: row 'NAME' left out: ...`` where the estimator of such a row
    raises (the other rows are kept); without it that error is raised. ``leaked``: a list that collects
    ``ID: MODEL (rows ...) trained on ...`` for a model trained or selected on epochs of the test split
    (``seen_test_epochs``); without it each is a ``SeenTestEpochsWarning``. ``untrained``: a list that collects
    ``MODEL (rows ...) holds no training: ...`` once for each model that is epoch 0 of a run from scratch
    (``models_without_training``); without it each is an ``UntrainedModelWarning``.
    """
    ids = datasets.present(dataset_ids)
    rows_of = {dataset_id: methods(model_dir, dataset_id, extra) for dataset_id in ids}    # names checked first
    own = {m.name for m in extra}
    all_rows, rtk_rows, said = [], [], set()
    for dataset_id in ids:
        plugins = _made(rows_of[dataset_id], own, dataset_id, left_out)
        try:                        # reading the dataset: bad files cost this dataset only (estimator bugs do not)
            span, k = scored_span(dataset_id, _features_for(e for _, e in plugins), warm_up)
        except (*INPUT_ERRORS, OSError) as err:
            if failed is None:
                raise
            failed.append(f"{dataset_id}: not run ({input_line(err)})")
            continue
        for line in models_that_saw_test_epochs(dataset_id, plugins, span.subset(slice(k, None))):
            if leaked is None:
                warnings.warn(line, SeenTestEpochsWarning, stacklevel=2)
            else:
                leaked.append(line)
        for line in models_without_training(plugins):
            if line in said:                    # a model file is untrained on every dataset: said once
                continue
            said.add(line)
            if untrained is None:
                warnings.warn(line, UntrainedModelWarning, stacklevel=2)
            else:
                untrained.append(line)
        rows, rtk, solutions, truth = dataset_rows(dataset_id, plugins, span, k, own, left_out)
        all_rows += rows
        rtk_rows += rtk
        if plots and out_dir is not None and solutions:
            _plot(out_dir / "figures", dataset_id, solutions, truth, unwritten)
    return all_rows, rtk_rows


class SeenTestEpochsWarning(UserWarning):
    """A model was trained or selected on epochs of the test split it is scored on (``run`` without ``leaked``)."""


class UntrainedModelWarning(UserWarning):
    """A row's model holds no training: epoch 0 of a run from scratch (``run`` without ``untrained``)."""


def _learned_models(plugins: list[tuple[str, object]]) -> dict[str, tuple[object, list[str]]]:
    """The model files of the learned rows among (row name, estimator) ``plugins``: path -> (model, its row names)."""
    models: dict[str, tuple[object, list[str]]] = {}
    for name, estimator in plugins:
        noise = getattr(estimator, "noise", None)
        if isinstance(getattr(noise, "metadata", None), dict):
            models.setdefault(str(getattr(noise, "path", None)), (noise, []))[1].append(name)
    return models


def _rows_text(names: list[str]) -> str:
    """``rows 'A', 'B'``: the rows a model file is used in."""
    return f"rows {', '.join(repr(r) for r in names)}"


def models_that_saw_test_epochs(dataset_id: str, plugins: list[tuple[str, object]], test: Sequence) -> list[str]:
    """``ID: MODEL (rows ...) trained on ...`` for each learned row's model that saw epochs of the test split ``test``.

    A model is named once however many rows use it; its training pieces are compared by time and place, so the same
    drive registered under another id or file (or a co-located receiver's) is caught too (``seen_test_epochs``).
    """
    from learning.export import seen_test_epochs

    models = _learned_models(plugins)
    if not models:
        return []
    obs, scored = datasets.obs_hashes(dataset_id), test.labelled
    return [f"{dataset_id}: {Path(path).name} ({_rows_text(rows)}) {line}"
            for path, (noise, rows) in models.items()
            for line in seen_test_epochs(noise.metadata, dataset_id, test.time_gps_s[scored],
                                         test.truth_ecef_m[scored], obs)]


def models_without_training(plugins: list[tuple[str, object]]) -> list[str]:
    """``MODEL (rows ...) holds no training: ...`` for each learned row's model that is epoch 0 of a run from scratch,
    the random network (``learning.export.untrained_reason``, as ``lfgnss.solve`` warns of it)."""
    from learning.export import untrained_reason

    lines = []
    for path, (noise, rows) in _learned_models(plugins).items():
        reason = untrained_reason(noise)
        if reason is not None:
            lines.append(f"{path} ({_rows_text(rows)}) {reason}")
    return lines


def _plot(folder: Path, dataset_id: str, solutions: dict, truth: np.ndarray, unwritten: list[str] | None) -> None:
    """The dataset's CDF, track and error PNGs: the LF-GNSS EKF (of ``--models``; else the first row) and the rest."""
    from .outputs import plot_solution

    main_name = next((name for name in solutions if split_label(name)[0] == MAIN_EKF), next(iter(solutions)))
    others = {name: sol for name, sol in solutions.items() if name != main_name}
    try:
        plot_solution(folder, solutions[main_name], truth, extra_solutions=others, prefix=f"{dataset_id}-",
                      label=main_name, title=f"{dataset_id}, test split (python -m lfgnss.benchmark)")
    except OSError as err:
        if unwritten is None:
            raise
        unwritten.append(f"{err.filename or folder}: {cannot_write(err)}")


@contextmanager
def _own_code(name: str, own: Collection[str], dataset_id: str, left_out: list[str] | None) -> Iterator[None]:
    """Around a row's estimator: an error in the code of one of one's ``own`` rows costs that row on this dataset,
    noted in ``left_out`` (raised without it); the built-in rows' errors are raised."""
    try:
        yield
    except Exception as err:  # any bug of the user's code; Ctrl-C still stops the run
        if left_out is None or name not in own:
            raise
        left_out.append(f"{dataset_id}: row {name!r} left out: its estimator raised {type(err).__name__}: "
                        f"{shortened(one_line(err), 300)}")


def _made(rows: list[Method], own: Collection[str], dataset_id: str,
          left_out: list[str] | None) -> list[tuple[str, object]]:
    """(row name, estimator) pairs of ``rows``; one of one's ``own`` that cannot be made is left out (``_own_code``)."""
    made = []
    for m in rows:
        with _own_code(m.name, own, dataset_id, left_out):
            made.append((m.name, m.create()))
    return made


def dataset_rows(dataset_id: str, plugins: list[tuple[str, object]], span: Sequence, k: int = 0,
                 own: Collection[str] = (), left_out: list[str] | None = None
                 ) -> tuple[list[dict], list[dict], dict, np.ndarray]:
    """One dataset's rows over all test epochs and over RTKLIB's solved ones, the Solutions by row name, the truth.

    ``plugins``: (row name, estimator) pairs; ``span``, ``k``: ``scored_span``'s sequence and warm-up epochs;
    ``own``, ``left_out``: the names of rows of one's own, whose errors ``left_out`` collects (``_own_code``).
    """
    from estimators.base import STATUS_NONE, STATUS_UPDATED, Solution

    spec = datasets.get(dataset_id)
    test = span.subset(slice(k, None))
    truth = test.truth_ecef_m
    with tempfile.TemporaryDirectory() as tmp:
        rtk_pos, _ = _rtklib_on(test, spec, Path(tmp))
    rows, rtk_rows, solutions = [], [], {}
    ok = np.zeros(len(test), bool) if rtk_pos is None else np.all(np.isfinite(rtk_pos), axis=1)
    if rtk_pos is not None:
        rows.append(accuracy_table(rtk_pos, truth, ok, dataset=dataset_id, method=RTKLIB,
                                   trained_on="-") | {"epochs_per_s": float("nan")})
    for name, estimator in plugins:
        with _own_code(name, own, dataset_id, left_out):
            row, rtk_row, solutions[name] = _scored(dataset_id, name, estimator, span, k, truth, ok)
            rows.append(row)
            if rtk_row is not None:
                rtk_rows.append(rtk_row)
    if ok.any():
        rtk_rows.append(accuracy_table(rtk_pos[ok], truth[ok], ok[ok], dataset=dataset_id,
                                       method=RTKLIB, trained_on="-"))
        solutions["RTKLIB"] = Solution("rtklib", test.time_gps_s, rtk_pos, np.zeros((len(test), 3, 3)),
                                       np.zeros(len(test)), np.zeros(len(test), int),
                                       np.where(ok, STATUS_UPDATED, STATUS_NONE))
    return rows, rtk_rows, solutions, truth


def _scored(dataset_id: str, name: str, estimator, span: Sequence, k: int, truth: np.ndarray,
            ok: np.ndarray) -> tuple[dict, dict | None, object]:
    """A row's figures over all test epochs and over RTKLIB's solved ones (``ok``; None if none), and its Solution."""
    start = time.perf_counter()
    sol = _checked_solution(estimator.solve(span), len(span))
    rate = len(span) / (time.perf_counter() - start)
    sol = sol.subset(slice(k, None)) if k else sol
    trained = _trained_on(getattr(estimator, "noise", None))
    row = accuracy_table(sol.pos_ecef_m, truth, sol.available, dataset=dataset_id, method=name,
                         trained_on=trained) | {"epochs_per_s": rate}
    rtk_row = accuracy_table(sol.pos_ecef_m[ok], truth[ok], sol.available[ok], dataset=dataset_id, method=name,
                             trained_on=trained) if ok.any() else None
    return row, rtk_row, sol


def _checked_solution(sol: object, epochs: int):
    """``sol`` if it is a Solution with ``epochs`` epochs; TypeError or ValueError saying what it is instead."""
    from estimators.base import Solution

    if not isinstance(sol, Solution):
        raise TypeError(f"solve returned {type(sol).__name__}, not an estimators.Solution")
    if len(sol) != epochs:
        raise ValueError(f"solve returned {len(sol)} epochs for a sequence of {epochs}")
    return sol


def _trained_on(noise) -> str:
    """Datasets and split a learned noise model was trained on ('-' for hand-set noise); ``, untrained (epoch 0)``
    added for a model that holds no training (``learning.export.untrained_reason``)."""
    from learning.export import trained_on, untrained_reason

    meta = getattr(noise, "metadata", None)
    if meta is None:
        return "-"
    reason = untrained_reason(noise)
    if reason is None:
        return trained_on(meta)
    member = f"{reason.split(' of ')[0]} " if reason.startswith("member") else ""     # "member 1 " of an ensemble
    return f"{trained_on(meta)}, {member}untrained (epoch 0)"


_COLUMNS = ("dataset", "method", "trained_on", *METRIC_COLUMNS, "epochs_per_s")


def _select(rows: list[dict]) -> list[dict]:
    """The rows cut to the columns of the results tables (every metric of ``accuracy_table``)."""
    return [{k: r[k] for k in _COLUMNS if k in r} for r in rows]


def target_rows(all_rows: list[dict], rtk_rows: list[dict]) -> list[dict]:
    """Each learned EKF/FGO row against the targets, the plain EKF, the yardstick and RTKLIB (on its epochs).

    Cells read ``figure (yes|no)``: whether this row's 3D (or 2D) RMSE [m] is at or below the bar. The rows are those
    whose name starts with ``LF-GNSS`` (not the ablations); a model file's rows are read by their built-in name
    (``split_label``), the plain EKF in its filter with the same ``file_label``.
    """
    def fig(rows: list[dict], dataset: str, method: str, key: str) -> float:
        found = [r[key] for r in rows if r["dataset"] == dataset and r["method"] == method]
        return float(found[0]) if found else float("nan")

    def versus(value: float, bar: float) -> str:
        if not (np.isfinite(value) and np.isfinite(bar)):
            return "-"
        return f"{value:.2f} vs {bar:.2f} ({'yes' if value <= bar else 'no'})"

    out = []
    for r in all_rows:
        d, m = r["dataset"], r["method"]
        if not m.startswith("LF-GNSS") or " w/o " in m:
            continue
        t3, t2 = TARGETS.get(d, (float("nan"), float("nan")))
        base, label = split_label(m)        # "LF-GNSS EKF (FGO)": a file name never makes it a smoother
        smoother = "FGO" in base or RTS in base     # uses later epochs too: against the yardstick's batch graph
        y3, y2 = (YARDSTICK_GRAPH if smoother else YARDSTICK_EKF).get(d, (float("nan"), float("nan")))
        plain = PLAIN_RTS if RTS in base else PLAIN
        own = {OWN_EKF: PLAIN_OWN_FILTER, MAIN_EKF: PLAIN_MAIN_FILTER + label}.get(base)
        if own is not None and np.isfinite(fig(all_rows, d, own, "rmse_3d_m")):
            plain = own                     # the stronger bar: the same filter, hand-set noise
        out.append({"dataset": d, "method": m, "trained_on": r.get("trained_on", "-"),
                    "3D vs target": versus(r["rmse_3d_m"], t3), "2D vs target": versus(r["rmse_2d_m"], t2),
                    "3D vs plain EKF": versus(r["rmse_3d_m"], fig(all_rows, d, plain, "rmse_3d_m")),
                    "3D vs yardstick": versus(r["rmse_3d_m"], y3), "2D vs yardstick": versus(r["rmse_2d_m"], y2),
                    "3D vs RTKLIB, its epochs": versus(fig(rtk_rows, d, m, "rmse_3d_m"),
                                                       fig(rtk_rows, d, RTKLIB, "rmse_3d_m")),
                    "2D vs RTKLIB, its epochs": versus(fig(rtk_rows, d, m, "rmse_2d_m"),
                                                       fig(rtk_rows, d, RTKLIB, "rmse_2d_m"))})
    return out


def model_files(model_dir: Path, ids: list[str]) -> list[Path]:
    """The model files a run over ``ids`` reads from ``--models`` (a folder, matched by name, or one file)."""
    if Path(model_dir).is_file():
        return [Path(model_dir)]
    return [Path(model_dir) / n for n in expected_model_names(ids) if (Path(model_dir) / n).is_file()]


def provenance_text(models: list[Path], out: Path | None = None) -> str:
    """results.md's line on what made the figures: lfgnss's version, the code's git commit (changes under the run's
    ``out`` folder aside: regenerating docs/ rewrites tracked files), each model's SHA-256."""
    from learning.provenance import code_text, git_state

    from . import __version__
    from .paths import file_hash

    digests = ", ".join(f"`{m.name}` {file_hash(m, content=False)}" for m in models)
    code = code_text(git_state(ignore=(out,) if out else ()))
    return f"Code: lfgnss {__version__}, {code}. Model files (SHA-256, first 16 hex digits): {digests or 'none'}."


def _no_rtklib_rows(all_rows: list[dict]) -> str:
    """Why the table of RTKLIB's epochs is empty: RTKLIB did not run, or it solved no labelled test epoch."""
    ran = [r["dataset"] for r in all_rows if r["method"] == RTKLIB]
    if not ran:
        return "RTKLIB not installed (or it failed on every dataset): no rows."
    return f"RTKLIB solved no labelled test epoch of {', '.join(ran)} (its chi-square test rejected them all): no rows."


def write_report(path: Path, all_rows: list[dict], rtk_rows: list[dict], command: str,
                 warm_up: str | None = None, figures: bool = True, failed: list[str] = (),
                 made_by: str = "", left_out: list[str] = (), leaked: list[str] = (),
                 untrained: list[str] = ()) -> Path:
    """Markdown results file with both tables and how they were made.

    ``warm_up``: the split the filters started at; ``failed``: ``ID: reason`` of datasets that could not be run;
    ``made_by``: the code and model files (``provenance_text``); ``left_out``: rows of one's own whose estimator
    raised (``run``); ``leaked``: models trained or selected on test epochs (``run``); ``untrained``: models that hold
    no training (``run``).
    """
    targets = target_rows(all_rows, rtk_rows)
    start = "" if warm_up is None else (
        f" Every estimator starts at the first labelled epoch of the {warm_up} split and runs on through the test "
        f"split, so the filters enter it warm, as in a receiver that has been running; the {warm_up} epochs' "
        "observations are used, never their truth, and only test epochs are scored (`--warm-up`). Without it the "
        "filters start cold on the test split's first epoch (docs/results.md).")
    text = [
        "# lfgnss benchmark results" + ("" if warm_up is None else f", filters warmed up on the {warm_up} split"),
        "",
        f"Produced by `{command}` (protocol: shared/BENCHMARK.md; test splits only; RMSE in metres in the local "
        "ENU frame of the ground truth; availability = share of labelled test epochs with a solution; "
        "epochs/s = estimator stage only, this machine, one run)." + start + (
            "" if warm_up is None else " The targets table reads these figures against BENCHMARK.md's bars and "
            "yardstick, which are stated for the test split without saying where the filter starts; whether a warm "
            "start is the protocol's is for the team (README, Results)."),
        *(["", made_by] if made_by else []),
        "",
        *([f"**Not run** (bad input; the tables leave these datasets out): {'; '.join(failed)}.", ""]
          if failed else []),
        *([f"**Rows left out** (the estimator of one's own raised; the tables leave that row out on that dataset): "
           f"{'; '.join(left_out)}.", ""] if left_out else []),
        *([f"**Trained on test epochs** (these rows' figures are not held-out results): {'; '.join(leaked)}.", ""]
          if leaked else []),
        *([f"**Untrained models** (epoch 0 of a run from scratch, the random network: these rows' figures are no "
           f"learned noise's): {'; '.join(untrained)}.", ""] if untrained else []),
        "## All labelled test epochs",
        "",
        format_markdown(_select(all_rows)),
        "",
        "## Epochs that RTKLIB solved (its chi-square test rejects the rest)",
        "",
        format_markdown(_select(rtk_rows)) if rtk_rows else _no_rtklib_rows(all_rows),
        "",
        "## Against the targets",
        "",
        "Targets are BENCHMARK.md's for the learned EKF (3D / 2D RMSE); the yardstick is its independent EKF for "
        "EKF rows and its robust batch graph for FGO and RTS-smoothed rows (both use later epochs); smoothed rows "
        "are compared with the smoothed plain EKF (in the default filter), and the LF-GNSS and per-dataset EKFs with "
        "the plain EKF in their own filter where that row exists, the FGO rows with the forward plain EKF in the default "
        "filter (there is no plain graph row); RTKLIB is compared on the epochs it solved. `yes`: "
        "at or below the bar. Why figures fall short is discussed in the README's Results section.",
        "",
        markdown_table(targets) if targets else "No learned rows (no model files).\n",
        "",
        "Figures: `figures/<dataset>-cdf.png`, `-track.png`, `-errors.png`." if figures
        else "No figures (`--no-plots`).",
        "",
    ]
    path.parent.mkdir(parents=True, exist_ok=True)
    write_output(path, lambda target: target.write_text("\n".join(text)))   # whole, or the previous file stays
    return path


def _prepare_out(out: Path, plots: bool) -> Path:
    """Create ``--out`` before any work, so that a folder that cannot hold the results costs no run; its results.md."""
    report, figures = out / "results.md", out / "figures"
    make_output_folder(out)
    try:
        if report.is_dir():
            raise InputError(report, "cannot write (a folder of that name is in the way)")
        if plots and figures.exists() and not figures.is_dir():
            raise InputError(figures, "cannot write the figures (a file of that name is in the way; --no-plots "
                                      "skips them)")
    except OSError as err:
        raise InputError(err.filename or out, f"cannot create the output folder ({err.strerror or err})") from None
    return report


def _refuse_partial_docs(args: argparse.Namespace, ids: list[str]) -> None:
    """InputError unless a run into the repository's docs/ (its committed results) is the whole default run: all three
    benchmark datasets present, the bundled models, no dataset or estimator (--plugin, --backend) of one's own; a part
    would replace the whole table, and rows of one's own are no part of the committed results."""
    from .paths import REPO_DIR

    committed = (REPO_DIR / "docs").resolve()
    out = Path(args.out).resolve()
    if out != committed and committed not in out.parents:
        return
    what = ([f"--register {', '.join(map(str, args.register))}"] if args.register else []) \
        + ([f"--models {args.models}"] if Path(args.models).resolve() != MODEL_DIR.resolve() else []) \
        + [f"--{option} {name}" for option in ("plugin", "backend") for name in getattr(args, option, None) or ()] \
        + ([f"datasets {', '.join(ids) or '(none present)'} only"] if tuple(ids) != DEFAULT_DATASETS else [])
    if what:
        raise InputError(args.out, f"holds the committed results of the whole default run (all of "
                                   f"{', '.join(DEFAULT_DATASETS)}, the bundled models); this run ({'; '.join(what)}) "
                                   "would replace them with a part: give another --out")


class _GivenOnce(argparse.Action):
    """An option that takes one value: given again, an option error (argparse would keep the last one silently)."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: object,
                 option_string: str | None = None) -> None:
        before = getattr(namespace, self.dest)
        if before is not self.default:
            parser.error(f"argument {option_string}: given twice ({before}, then {values}); it takes one model file "
                         "or folder: to compare two model files, run the benchmark once for each, with its own --out")
        setattr(namespace, self.dest, values)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and write the results file.

    Exit status 0; 2 for bad input (one line ``error: ...``, before any work where it can be seen then: a --plugin
    that does not import, an unknown --backend), a results file or figure that could not be written, or a --backend
    row whose estimator raised (the tables are printed all the same, without what is lost); 3 for an internal error;
    130 for Ctrl-C.
    """
    p = argparse.ArgumentParser(prog="python -m lfgnss.benchmark", description=__doc__.split("\n\n")[0],
                                formatter_class=PlainHelp)
    p.add_argument("datasets", nargs="*", default=[],
                   help=f"dataset ids: {', '.join(DEFAULT_DATASETS)} (the benchmark datasets of shared/BENCHMARK.md) "
                        "or the id of a --register'ed file (default: all three, or only the --register'ed ones)")
    p.add_argument("--register", action="append", default=[], metavar="FILE.toml",
                   help="a dataset of your own (lfgnss.datasets TOML), run too; repeatable")
    p.add_argument("--models", type=path_option, default=MODEL_DIR, action=_GivenOnce,
                   help=f"folder of model files matched to the rows by name: {DEFAULT_MODEL} gives the shipped "
                        f"model's rows (LF-GNSS EKF, + RTS smoother, FGO) and {', '.join(ABLATIONS.values())} the "
                        "ablation rows, on every dataset; lfgnss-<dataset id>.npz gives the per-dataset model's rows "
                        "on that dataset only; other files are not used. Or one model file, which takes the shipped "
                        "model's rows on every dataset, named after the file as lfgnss.solve names its outputs: "
                        "LF-GNSS EKF (mine), ... for mine.npz; LF-GNSS EKF (x), LF-GNSS EKF + RTS smoother (x), "
                        "LF-GNSS FGO (x) for a run's runs/x/model.npz (default: the bundled models, "
                        "lfgnss/data/model); given once")
    p.add_argument("--out", type=path_option, default=None,
                   help="folder for results.md and figures/ (default: lfgnss-benchmark in the current folder, "
                        "lfgnss-benchmark/warm-up-SPLIT with --warm-up; --out docs, and --out docs/warm-up-val "
                        "with --warm-up val, regenerate the repository's committed results: the whole default "
                        "run only, all three datasets with the bundled models)")
    p.add_argument("--warm-up", choices=WARM_UP, default=None, metavar="SPLIT",
                   help="start every estimator at the first epoch of this split (train or val; its observations, "
                        "never its truth) and score the test split only, so the filters enter it warm")
    p.add_argument("--plugin", action="append", default=[], metavar="MODULE_OR_FILE",
                   help="a .py file (by its path) or a Python module (by its dotted name) imported before the run, "
                        "whose import registers estimators of your own: @estimators.register(\"NAME\") on the class; "
                        "repeatable")
    p.add_argument("--backend", action="append", default=[], metavar="NAME",
                   help="a row named NAME on every dataset, after the built-in ones: the registered back end NAME "
                        "(one of estimators.available(), or of a --plugin) made with estimators.create(NAME), no "
                        "options and no model file; repeatable. The targets table reads only LF-GNSS rows (names "
                        "starting with LF-GNSS), so such a row is in the results tables only")
    p.add_argument("--no-plots", action="store_true", help="skip the CDF, track and error PNGs")
    args = p.parse_args(argv)
    if args.out is None:            # never the repository's docs/ unless asked for (--out docs)
        root = Path(DEFAULT_OUT)
        args.out = root if args.warm_up is None else root / f"warm-up-{args.warm_up}"
    return run_command(lambda: _main(args, argv), "the benchmark")


def _nothing_run(failed: list[str], report: Path) -> InputError:
    """The error of a run in which no dataset could be run (``report`` is not written); the other failures are
    printed first, one line each."""
    for message in failed[:-1]:
        print(f"error: {message}", file=sys.stderr)
    return InputError(report, f"not written: no dataset could be run ({failed[-1]})")


def _main(args: argparse.Namespace, argv: list[str] | None) -> int:
    """``main`` after parsing: check everything, run, write results.md, then print the tables."""
    if args.plugin or args.backend:     # refused into docs/ before a plugin's code runs
        _refuse_partial_docs(args, list(DEFAULT_DATASETS))
    extra = own_rows(args.plugin, args.backend)
    ids = resolve_datasets(args.datasets, args.register, ("test",) + ((args.warm_up,) if args.warm_up else ()))
    for message in check_models(args.models, ids):
        print(f"warning: {message}", file=sys.stderr)
    for dataset_id in ids:          # a --backend named as a built-in row is refused here, before any work
        methods(args.models, dataset_id, extra)
    # a dataset of one's own whose files are missing is an error (exit 2); the benchmark sets' absent data a note
    lost = [i for i in ids if datasets.get(i).source is not None and datasets.get(i).missing()]
    failed = [f"{i}: not run ({datasets.get(i).missing_note()})" for i in lost]
    asked, ids = ids, datasets.present([i for i in ids if i not in lost])
    _refuse_partial_docs(args, ids)
    if not ids and failed:
        raise _nothing_run(failed, args.out / "results.md")
    if not ids:
        first = datasets.get(asked[0]).missing()[0]
        raise InputError(args.out / "results.md", f"not written: no dataset has all its files (first missing: "
                                                  f"{first}){datasets.shared_data_hint(first)}")
    made_by = provenance_text(model_files(args.models, ids), args.out)     # before the run writes anything
    report = _prepare_out(args.out, plots=not args.no_plots)
    unwritten: list[str] = []      # figures and results.md that could not be written: the rest is kept, exit 2
    left_out: list[str] = []       # --backend rows whose estimator raised: the other rows are kept, exit 2
    leaked: list[str] = []         # models trained on test epochs: said in results.md and as warnings
    untrained: list[str] = []      # models that hold no training: said in results.md and as warnings
    # datasets whose files are missing or turn out bad (failed, above): the others are kept, exit 2
    all_rows, rtk_rows = run(ids, model_dir=args.models, out_dir=args.out, plots=not args.no_plots,
                             unwritten=unwritten, warm_up=args.warm_up, failed=failed, extra=extra, left_out=left_out,
                             leaked=leaked, untrained=untrained)
    if failed and not all_rows:    # an empty table never replaces a results file
        raise _nothing_run(failed, report)
    argv = sys.argv[1:] if argv is None else argv
    command = shlex.join(["python", "-m", "lfgnss.benchmark", *argv])
    try:                            # before the tables go to stdout, which may be a pipe closed early (| head)
        written = write_report(report, all_rows, rtk_rows, command, args.warm_up, not args.no_plots, failed, made_by,
                               left_out, leaked, untrained)
    except OSError as err:
        written = None
        unwritten.append(f"{err.filename or report}: {cannot_write(err)}")
    try:
        print(format_text(_select(all_rows)))
        if rtk_rows:
            print("\nOn the epochs RTKLIB solved:")
            print(format_text(_select(rtk_rows)))
        if written is not None:
            print(f"\nwritten: {written}")
        sys.stdout.flush()
    except BrokenPipeError:         # the reader went away: results.md is written, nothing more to say on stdout
        stdout_gone()
    for message in leaked + untrained:
        print(f"warning: {message}", file=sys.stderr)
    for message in failed + left_out + unwritten:
        print(f"error: {message}", file=sys.stderr)
    return 2 if failed or left_out or unwritten else 0


if __name__ == "__main__":
    raise SystemExit(main())
