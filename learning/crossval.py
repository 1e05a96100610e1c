"""Blocked K-fold cross-validation of a training recipe on the train + validation epochs (never test).

    python -m learning.crossval --config learning/configs/default.toml --folds 3 [--set key=value ...]
                                [--fold J ...] [--out runs/cv-NAME] [--no-progress]
                                [--reuse DIR --set ekf.KEY=VALUE]      # rescore saved folds in another filter
                                [--reuse DIR0 --reuse DIR1 ... [--combine mixture]]   # score the ensemble of
                                                                       # runs' fold models
    python -m learning.crossval --folds 3 --pool DIR0 --pool DIR1 --pool DIR2 --out DIR   # join --fold runs

A validation split of a minute or two is one street: whether a recipe generalises cannot be read from
it. Here each dataset's train and validation epochs, in time order and joined where they are contiguous
(``cv_sequences``), are cut into ``K`` contiguous blocks; fold ``j`` trains on the other blocks (as separate
sequences where the held-out block cuts them) and evaluates on block ``j``, once per training epoch, exactly as
``learning.train`` evaluates its validation split. Each fold also runs the plain EKF (hand-set C/N0-elevation R, no
v^c, the same EKF settings) on its held-out block, the bar the learned model has to clear.

Reported per fold and pooled over folds (RMSE pooled by each fold's labelled epochs, ``labelled_epochs``, which its
RMSEs are over; an epoch before a piece's first fix, unsolved, still counts):
the plain EKF, the untrained network (epoch 0), the last epoch (the honest figure of a fixed schedule) and the best
epoch (optimistic: it is picked on the held-out block itself); and the plain EKF and the last epoch with the RTS
smoother (``estimators.smoother``; training itself reads smoothed positions only with ``train.smooth``); and the 2D
(horizontal) RMSE of the plain EKF and of the last epoch.
"untrained" has a random output head, so it is near, not equal to, the plain EKF even for a recipe with
the hand-set R prior; with ``train.init`` it is that starting model, the one fine-tuning has to beat (crossval.md
says so under its table). Each fold prints a header line (what it trains on and holds out) before its epoch
lines, whose "val 3D RMSE" is on the held-out block. Writes ``crossval.csv`` and ``crossval.md``
in ``--out`` and each fold's run (``log.csv``, ``curves.png``, ``best.pt``, ``last.pt``) in ``--out/fold<j>/``.
``--fold J`` (repeatable) runs only those folds, e.g. one process per fold on a machine with spare cores, each
with its own ``--out``; the pooled row is written only when every fold ran. ``--pool DIR`` (repeatable) then puts
those runs' folds in one table with the pooled rows, training and scoring nothing (each fold once, one recipe):
``python -m learning.crossval --folds 3 --pool cv/f0 --pool cv/f1 --pool cv/f2 --out cv/all``.
crossval.md starts with the command that made it and the code's git commit; a run that trained every fold ends
with the ``learning.train`` command of its recipe (``next:``). With several datasets each fold also
gets a row per dataset (``J:ID``, its last epoch on that dataset's held-out pieces) and each dataset a pooled row
(``pooled:ID``): the overall pooled row is dominated by the datasets with the most epochs.

``--reuse DIR`` trains nothing: it scores each fold's saved model (``DIR/fold<j>/last.pt``, from an earlier run of the
same recipe) again on its held-out block, under this run's ``[ekf]`` settings, e.g. ``--set ekf.huber_k=2``: an
inference-time variant of the filter judged on every block in a minute instead of a retraining. Anything else that
differs from the saved run's configuration (seed included) is refused; so is a held-out block whose data changed.
A fold model trained on another machine (its held-out block's features differ in the last digits: the same input
files, epochs, dataset TOML settings and, to rounding, normalisation) is scored here with a warning.
``--reuse`` repeated (runs of one recipe with different ``--set seed=S``) scores, per fold, the ensemble of the runs'
fold models (``learning.network.NetworkEnsemble``, as ``python -m learning.export`` writes several checkpoints):
their seeds may differ, nothing else; ``--combine mixture`` combines the members as a moment-matched Gaussian
mixture instead of by the geometric mean of their R (``learning.network.combine_members``). The "untrained" and
"best" columns are empty there; a fold checkpoint that did not reach ``train.epochs`` (its fold was interrupted or
diverged), or whose weights do not load or are not finite, is refused.

A run stopped among its folds (Ctrl-C, a diverged fold, a bad checkpoint) writes the finished folds' rows to
``crossval.csv`` / ``crossval.md`` before it ends; bad options and an unusable ``--out`` are refused before any work
(docs/bad_input.md, "Command lines").
"""
from __future__ import annotations

import argparse
import copy
import csv
import math
import re
import shlex
import sys
import warnings
from pathlib import Path

import numpy as np

from lfgnss.datasets import contiguous_runs, split_parts
from lfgnss.errors import (INPUT_ERRORS, InputError, cannot_write, input_line, one_line, path_option, shortened,
                           print_stdout, warnings_on_one_line)
from lfgnss.help_text import PlainHelp
from lfgnss.metrics import accuracy_table, markdown_table
from lfgnss.paths import check_output_folder, make_output_folder, model_path
from lfgnss.sequence import Sequence

from .data import signed_log_names
from .network import COMBINE_RULES, check_combine
from .normalise import Normaliser
from .provenance import code_text, command_line, git_state
from .train import (DEFAULT_CONFIG, _flat, _merge_free, adopt_init, config_path, ekf_config, exit_on_input_error,
                    init_model, load_config, load_sequences, prepare, read_checkpoint, torch_threads, train,
                    trained_datasets)

COLUMNS = ["fold", "held_out_epochs", "labelled_epochs", "plain_ekf_rmse_3d_m", "untrained_rmse_3d_m",
           "last_rmse_3d_m", "best_rmse_3d_m", "best_epoch", "plain_ekf_smoothed_rmse_3d_m", "last_smoothed_rmse_3d_m",
           "plain_ekf_rmse_2d_m", "last_rmse_2d_m"]


def fold_sequences(sequences: list[Sequence], folds: int, fold: int,
                   min_epochs: int = 2) -> tuple[list[Sequence], list[Sequence]]:
    """(training pieces, held-out pieces) of block ``fold`` of ``folds`` over the sequences' epochs in order.

    Pieces shorter than ``min_epochs`` are dropped (a filter needs more than one epoch to mean anything).
    """
    if not 0 <= fold < folds or folds < 2:
        raise ValueError(f"need 2 <= folds and 0 <= fold < folds, got fold {fold} of {folds}")
    total = sum(len(s) for s in sequences)
    if total < folds * min_epochs:
        raise ValueError(f"{total} epochs cannot make {folds} folds of at least {min_epochs} epochs")
    block = np.array_split(np.arange(total), folds)[fold]
    train, held, start = [], [], 0
    for seq in sequences:
        local = np.arange(len(seq))
        in_block = (local + start >= block[0]) & (local + start <= block[-1])
        for part, bucket, tag in ((~in_block, train, "cv-train"), (in_block, held, "cv-held-out")):
            for k, run in enumerate(contiguous_runs(np.flatnonzero(part))):
                if run.size >= min_epochs:
                    bucket.append(seq.subset(slice(run[0], run[-1] + 1), name=f"{seq.name}/{tag}{fold}.{k}"))
        start += len(seq)
    return train, held


def cv_sequences(config: dict) -> dict[str, list[Sequence]]:
    """Per dataset of ``config``, the epochs cross-validation cuts into blocks: its train and validation splits as one
    split, so epochs contiguous across their boundary stay one piece (a block or a training piece is not cut there)."""
    data = config["data"]
    return {ds: load_sequences(ds, f"{data['train_split']}+{data['val_split']}", config) for ds in data["datasets"]}


def plain_ekf_rmse_m(sequences: list[Sequence], config: dict, smooth: bool = False) -> tuple[float, float]:
    """(3D, 2D) RMSE [m] of the plain EKF (``smooth``: RTS-smoothed) over the labelled epochs of ``sequences``, pooled."""
    from estimators.ekf import PlainEkf

    rows = []
    for seq in sequences:
        sol = PlainEkf(config=ekf_config(config), smooth=smooth).solve(seq)
        rows.append(accuracy_table(sol.pos_ecef_m, seq.truth_ecef_m, sol.available))
    counts = [r["n_solved"] for r in rows]
    return tuple(pooled_rmse([r[k] for r in rows], counts) for k in ("rmse_3d_m", "rmse_2d_m"))


def _saved_rmse_m(checkpoint: Path, config: dict, prep) -> tuple[dict, float, float]:
    """A fold's saved checkpoint, read once, and its (RTS-smoothed 3D, forward 2D) RMSE [m] over the held-out block."""
    saved = read_checkpoint(checkpoint)
    return (saved, *_model_rmse_m([saved], config, prep.val_batches, prep.n_systems)[1:])


def _model_rmse_m(saved: list[dict], config: dict, batches: list, n_systems: int, combine: str = "geometric"
                  ) -> tuple[float, float, float]:
    """(3D as trained (forward, or smoothed with ``train.smooth``), RTS-smoothed 3D, forward 2D) RMSE [m] of
    checkpoints' weights (several: their ensemble, members combined by the rule ``combine``) over ``batches``, under
    ``config``'s EKF."""
    from .network import NetworkEnsemble
    from .train import checkpoint_network, evaluate

    nets = [checkpoint_network(s)[0] for s in saved]
    model = nets[0] if len(nets) == 1 else NetworkEnsemble(nets, combine)
    run = dict(n_systems=n_systems, ekf_cfg=ekf_config(config))
    smooth = bool(saved[0]["config"]["train"].get("smooth", False))    # the run's own last_rmse_3d_m: as trained
    return (evaluate(model, batches, smooth=smooth, **run)[0], evaluate(model, batches, smooth=True, **run)[0],
            evaluate(model, batches, up_weight=0.0, **run)[0])


#: Settings a rescore (``--reuse``) may change: the filter's, and how the run uses the machine.
RESCORE_FREE = ("ekf", "threads", "device")


def _recipe(config: dict, free: tuple[str, ...] = RESCORE_FREE) -> dict:
    """What a rescore must not change: ``config`` but the ``free`` tables, defaults filled in, file paths resolved."""
    flat = _flat({k: v for k, v in _merge_free(DEFAULT_CONFIG, config).items() if k not in free})
    resolve = lambda p: str(Path(p).resolve()) if p else p          # noqa: E731 -- cfg/m.npz = /abs/cfg/m.npz
    init = flat.get("train.init", "")
    flat["train.init"] = str(model_path(init).resolve()) if init else init       # a bundled name: its file
    flat["data.register"] = [resolve(p) for p in flat.get("data.register", [])]
    return flat


def saved_fold(reuse_dir: str | Path, fold: int, config: dict, held: list[Sequence],
               free: tuple[str, ...] = RESCORE_FREE, trained: list[Sequence] | None = None) -> dict:
    """The checkpoint ``reuse_dir/fold<fold>/last.pt``, checked to be of ``config``'s recipe (the ``free`` settings
    aside) and of the held-out pieces ``held`` (to the last digit, or to rounding: ``_same_data_elsewhere``, which
    reads the fold's training pieces ``trained``)."""
    from .train import fingerprint

    path = Path(reuse_dir) / f"fold{fold}" / "last.pt"
    try:
        saved = read_checkpoint(path)
        saved_config, prints = saved["config"], saved["data_fingerprints"]
    except Exception as exc:            # torch.load raises many kinds on a file that is not a checkpoint
        raise ValueError(f"{path}: not a learning.train checkpoint ({type(exc).__name__}: {exc})") from exc
    was, now = _recipe(saved_config, free), _recipe(config, free)
    changed = sorted(k for k in was.keys() | now.keys() if was.get(k, "(unset)") != now.get(k, "(unset)"))
    if changed:
        k = changed[0]
        raise ValueError(f"{path}: trained with {k} = {was.get(k, '(unset)')!r}, this run has "
                         f"{now.get(k, '(unset)')!r}; a rescore may change only {', '.join(free)} settings")
    val = config["data"]["val_split"]
    trained_on = [(p["sequence"], p["sha256_16"]) for p in prints if p["split"] == val]
    if trained_on != [(s.name, fingerprint(s)) for s in held]:
        why = _same_data_elsewhere(saved, config, held, trained)
        if why is not None:
            raise ValueError(f"{path}: its held-out block is not this run's ({why})")
        warnings.warn(_other_features_note(path, saved), stacklevel=2)
    _check_weights(path, saved)
    return saved


def _same_data_elsewhere(saved: dict, config: dict, held: list[Sequence], trained: list[Sequence] | None
                         ) -> str | None:
    """None when a fold checkpoint whose held-out fingerprints differ from ``held``'s was trained on this data all the
    same, on another machine: the same pieces and epochs (held out and trained on), input files (SHA-256) and dataset
    TOML data settings, and a normaliser within rounding (``Normaliser.same_as``) of the one the fold's training
    pieces ``trained`` give here (or, with ``train.init``, of that model's). Else the reason in words."""
    from .train import dataset_toml_change, init_model, source_file_hashes

    val = config["data"]["val_split"]
    pieces = [(p["sequence"], p.get("epochs")) for p in saved["data_fingerprints"]]
    if ([q for q, p in zip(pieces, saved["data_fingerprints"]) if p["split"] == val] != [(s.name, len(s)) for s in held]
            or (trained is not None and [q for q, p in zip(pieces, saved["data_fingerprints"]) if p["split"] != val]
                != [(s.name, len(s)) for s in trained])):
        return ("another --folds, the data changed since it was trained, or an older learning.crossval cut it, which "
                "broke folds at the train/validation boundary")
    files = {ds: source_file_hashes(ds) for ds in config["data"]["datasets"]}
    if not any(files.values()) or saved.get("source_files") != files:
        return "its input files differ from this run's (or it recorded none)"
    for toml, text in ((saved.get("provenance") or {}).get("dataset_tomls") or {}).items():
        if not isinstance(text, str) or text.startswith("(not readable:"):     # not read when it was trained
            continue
        try:
            change = dataset_toml_change(text, Path(toml).read_text())
        except (OSError, UnicodeDecodeError):
            change = "it cannot be read now"
        if change is not None:
            return f"{toml}: {change} when it was trained"
    if trained is not None:
        init = init_model(config)
        logged = signed_log_names(config["data"]["signed_log"], saved["feature_names"], config["model"].get("r_prior"))
        here = init.normaliser if init is not None else Normaliser.fit(trained, saved["feature_names"], logged)
        if not here.same_as(Normaliser.from_dict(saved["normaliser"])):
            return ("its features are normalised otherwise than this run's beyond rounding: another train.init file, "
                    "or another version of lfgnss's front end")
    return None


def _other_features_note(path: Path, saved: dict) -> str:
    """The warning of a fold model rescored on held-out features that come from its input files and epochs but not
    to the last digit: another machine's arithmetic, or (where the code differs) another front end too."""
    from .provenance import code_text, git_state

    trained, here = (saved.get("provenance") or {}).get("git") or {}, git_state() or {}
    code = (f"; it was trained at {code_text(trained)} and this is {code_text(here)}: if lfgnss's front end differs "
            "between them, its figures here are not those it would have had"
            if trained and here and (trained.get("commit") != here.get("commit") or trained.get("dirty")
                                     or here.get("dirty")) else "")
    return (f"{path}: its held-out block's features differ in the last digits from those it was validated on when "
            f"trained (the same input files, epochs and normalisation: another machine's arithmetic); it is scored "
            f"on this machine's features{code}")


def saved_ensemble(reuse_dirs: list[str | Path], fold: int, config: dict, held: list[Sequence],
                   trained: list[Sequence] | None = None) -> list[dict]:
    """``saved_fold`` of each folder (``trained``: the fold's training pieces); several must be runs of one recipe
    that differ in their seed only (as ``learning.export`` takes an ensemble's members), on identically normalised
    features."""
    free = RESCORE_FREE + (("seed",) if len(reuse_dirs) > 1 else ())
    saved = [saved_fold(r, fold, config, held, free, trained) for r in reuse_dirs]
    seeds = [s["config"].get("seed") for s in saved]
    for r, s in zip(reuse_dirs[1:], saved[1:]):
        path = Path(r) / f"fold{fold}" / "last.pt"
        if seeds.count(s["config"].get("seed")) > 1:
            raise ValueError(f"{path}: trained with seed {s['config'].get('seed')}, as another --reuse folder's: an "
                             "ensemble's members are runs with different seeds")
        if not Normaliser.from_dict(s["normaliser"]).same_as(Normaliser.from_dict(saved[0]["normaliser"])):
            raise ValueError(f"{path}: its features are normalised otherwise than {reuse_dirs[0]}'s fold {fold}")
    return saved


def _check_weights(path: Path, saved: dict) -> None:
    """ValueError naming ``path`` unless the checkpoint's weights load into its network, are finite, and are those of
    its last training epoch (a fold interrupted or diverged mid-training leaves an earlier epoch's ``last.pt``)."""
    import torch

    from .train import checkpoint_network

    try:
        epoch, epochs = int(saved["epoch"]), int(saved["config"]["train"]["epochs"])
        int(saved["n_systems"])
        checkpoint_network(saved)
        bad = [k for k, v in saved["model"].items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    except Exception as exc:            # whatever a damaged checkpoint makes torch or the normaliser raise
        raise ValueError(f"{path}: not a usable learning.train checkpoint ({type(exc).__name__}: "
                         f"{shortened(one_line(exc), 200)})") from None
    if bad:
        raise ValueError(f"{path}: not a usable learning.train checkpoint (non-finite weights in {bad[0]})")
    if epoch < epochs:
        raise ValueError(f"{path}: saved at epoch {epoch} of {epochs} (train.epochs): the fold was interrupted or "
                         "diverged; cross-validate that fold again (--fold J) before rescoring it")


def _fold_row(fold: int, held: list[Sequence], config: dict, learned: dict) -> dict:
    """A crossval row: the ``learned`` model's columns, and the plain EKF's on the same held-out pieces."""
    plain_3d, plain_2d = plain_ekf_rmse_m(held, config)
    return {"fold": fold, "held_out_epochs": sum(len(s) for s in held),
            "labelled_epochs": int(sum(np.count_nonzero(s.labelled) for s in held)), "plain_ekf_rmse_3d_m": plain_3d,
            "plain_ekf_smoothed_rmse_3d_m": plain_ekf_rmse_m(held, config, smooth=True)[0],
            "plain_ekf_rmse_2d_m": plain_2d, **learned}


def _rescored_row(fold: int, saved: list[dict], config: dict, held: list[Sequence], combine: str = "geometric"
                  ) -> dict:
    """A crossval row for a saved fold model (several: their ensemble) scored again on its held-out pieces (no
    untrained / best figures)."""
    from .data import sequence_batch

    normaliser = Normaliser.from_dict(saved[0]["normaliser"])
    batches = [sequence_batch(s, normaliser, n_systems=int(saved[0]["n_systems"])) for s in held]
    last_3d, last_smoothed_3d, last_2d = _model_rmse_m(saved, config, batches, int(saved[0]["n_systems"]), combine)
    return _fold_row(fold, held, config, {"untrained_rmse_3d_m": math.nan, "last_rmse_3d_m": last_3d,
                                          "best_rmse_3d_m": math.nan, "best_epoch": "-",
                                          "last_smoothed_rmse_3d_m": last_smoothed_3d, "last_rmse_2d_m": last_2d})


def pooled_rmse(rmse: list[float], counts: list[int]) -> float:
    """One RMSE over parts with RMSEs ``rmse`` over ``counts`` epochs each; NaN when no epoch (parts of 0 are skipped)."""
    n = sum(counts)
    return math.sqrt(sum(r ** 2 * c for r, c in zip(rmse, counts) if c) / n) if n else float("nan")


def crossval(config: dict, folds: int, out_dir: str | Path, *, progress: bool = True,
             only: list[int] | None = None, reuse: str | Path | list[str | Path] | None = None,
             command: str | None = None,
             config_file: str | Path | None = None, epoch_lines: bool | None = None,
             combine: str = "geometric") -> list[dict]:
    """Train ``config`` on each fold (or the folds ``only``); one row per fold, plus a ``pooled`` row when all ran.

    ``reuse``: train nothing, score the folds' saved models in that folder under ``config``'s EKF (``saved_fold``);
    a list of folders: the ensemble of their fold models (runs of the recipe with different seeds), its members
    combined by the rule ``combine`` (``learning.network.combine_members``).
    ``command``: the command line, recorded at the top of crossval.md and in the folds' checkpoints.
    ``config_file``: the ``--config`` file ``config`` was read from, recorded in the folds' checkpoints as
    ``learning.train`` records it.
    ``epoch_lines``: print a header line per fold and ``learning.train``'s epoch lines on stdout (default: as
    ``progress``; the command line prints them, ``--no-progress`` or not).
    """
    epoch_lines = progress if epoch_lines is None else epoch_lines
    out = Path(out_dir)
    if isinstance(folds, bool) or not isinstance(folds, int) or folds < 2:
        raise ValueError(f"folds must be a whole number >= 2 (--folds), got {folds!r}")
    chosen = range(folds) if only is None else sorted(set(only))     # a range: --folds 10**9 allocates nothing
    if only is not None and (not chosen or not all(0 <= j < folds for j in chosen)):
        raise ValueError(f"folds to run must be among 0..{folds - 1}, got {only}")
    if set(split_parts(config["data"]["val_split"])) & set(split_parts(config["data"]["train_split"])):
        raise ValueError(f"data.val_split {config['data']['val_split']!r} is trained on (data.train_split "
                         f"{config['data']['train_split']!r}): cross-validation cuts the train and validation epochs "
                         "into blocks, so each epoch would be there twice, held out and trained on; give two splits "
                         "that share no epochs")
    _refuse_used_out(out)
    reuse = None if reuse is None else [reuse] if isinstance(reuse, (str, Path)) else list(reuse)
    if check_combine(combine) != COMBINE_RULES[0] and (reuse is None or len(reuse) < 2):
        raise ValueError(f"combine {combine!r} combines an ensemble's members: it needs two or more --reuse folders")
    missing = [p for r in reuse or [] for j in chosen if not (p := Path(r) / f"fold{j}" / "last.pt").is_file()]
    if missing:
        raise ValueError(f"{missing[0]}: no saved fold model (--reuse takes the --out folder of an earlier "
                         f"cross-validation of the same recipe and --folds; --folds {folds} asks for fold "
                         f"{missing[0].parent.name[4:]})")
    _make_out(out)
    config = adopt_init(config)
    data = config["data"]
    init = init_model(config)
    seen = sorted(set(data["datasets"]) & set(trained_datasets(init))) if init is not None else []
    if seen:
        print(f"warning: train.init {init.path} was trained on {', '.join(seen)}: the held-out blocks are not "
              "unseen data, so this cross-validation is optimistic", file=sys.stderr)
    whole = cv_sequences(config)
    for line in [] if init is None or seen else _init_saw_blocks(init, whole):
        print(f"warning: train.init {init.path} {line}: the held-out blocks are not unseen data, so this "
              "cross-validation is optimistic", file=sys.stderr)
    rows, started = [], None if init is None else str(init.path)
    try:
        # scoring too on ``threads`` CPU threads, as training: folds run side by side with threads = 1 would
        # otherwise each score on every core, and small torch kernels slow down several times on shared cores
        with torch_threads(int(config["threads"])):
            _run_folds(rows, chosen, folds, whole, config, out, progress, reuse, command, config_file, epoch_lines,
                       combine)
    except BaseException as exc:        # Ctrl-C, a diverged fold, a bad checkpoint: the finished folds' rows are kept
        exc.crossval_stopped = (out, None, [])
        if rows:
            try:
                _write_results(out, rows, command, started)
                exc.crossval_stopped = (out, out / "crossval.csv", [r["fold"] for r in rows
                                                                     if isinstance(r["fold"], int)])
            except UnwrittenResults:
                pass
        raise
    if len(chosen) == folds:
        rows.extend(pooled_rows(rows, list(whole) if len(whole) > 1 else []))
    _write_results(out, rows, command, started)
    return rows


def _init_saw_blocks(init, whole: dict[str, list[Sequence]], epochs_word: str = "epochs to cross-validate on"
                     ) -> list[str]:
    """Where the model fine-tuning starts from was trained on epochs of ``whole``'s sequences (per dataset id; the
    same drive under another dataset id or file: ``learning.export.seen_test_epochs``): the first such line per
    dataset, the epochs called ``epochs_word``."""
    from lfgnss.datasets import obs_hashes

    from .export import seen_test_epochs

    lines = []
    for dataset_id, sequences in whole.items():
        if dataset_id == "synthetic":
            continue
        times = np.concatenate([s.time_gps_s[s.labelled] for s in sequences])
        truth = np.concatenate([s.truth_ecef_m[s.labelled] for s in sequences])
        seen = seen_test_epochs(init.metadata, dataset_id, times, truth, obs_hashes(dataset_id),
                                epochs_word=epochs_word)
        lines += seen[:1]
    return lines


def _refuse_used_out(out: Path) -> None:
    """InputError or ValueError if ``--out`` is a file or already holds a cross-validation (checked before any work)."""
    check_output_folder(out)
    try:
        if any((out / name).exists() for name in ("crossval.csv", "crossval.md", "fold0")):
            raise ValueError(f"{out}: already holds a cross-validation; choose another --out")
    except OSError as err:              # a name too long, a file in the path, a missing disk
        raise InputError(out, f"cannot create the output folder ({err.strerror or err})") from None


def _make_out(out: Path) -> None:
    """Create ``--out`` (and its parents); InputError naming it if that fails (a read-only or full disk)."""
    make_output_folder(out)


def pooled_rows(rows: list[dict], datasets: list[str]) -> list[dict]:
    """The ``pooled`` row of the fold rows (fold an int), and with several ``datasets`` a ``pooled:ID`` row each."""
    keys = [k for k in COLUMNS if k.endswith("_m")]

    def pooled(label: str, group: list[dict]) -> dict:
        counts = [r["labelled_epochs"] for r in group]         # each fold's RMSEs are over its labelled epochs
        return {"fold": label, "held_out_epochs": sum(r["held_out_epochs"] for r in group),
                "labelled_epochs": sum(counts),
                **{k: pooled_rmse([r[k] for r in group], counts) for k in keys}, "best_epoch": "-"}

    return ([pooled("pooled", [r for r in rows if isinstance(r["fold"], int)])]
            + [pooled(f"pooled:{ds}", [r for r in rows if str(r["fold"]).endswith(f":{ds}")]) for ds in datasets])


def pool(run_dirs: list[str | Path], folds: int, out_dir: str | Path, command: str | None = None) -> list[dict]:
    """One table, pooled rows included, of parallel ``--fold J`` runs (their ``--out`` folders): nothing is trained
    or scored again. Each fold of ``folds`` must come from exactly one run, and every run from the same recipe."""
    out = Path(out_dir)
    if isinstance(folds, bool) or not isinstance(folds, int) or folds < 2:
        raise ValueError(f"folds must be a whole number >= 2 (--folds), got {folds!r}")
    _refuse_used_out(out)
    rows, source, recipe, started = [], {}, None, None
    for d in map(Path, run_dirs):
        table = d / "crossval.csv"
        try:
            with open(table, newline="") as fh:
                found = [_csv_row(r) for r in csv.DictReader(fh)]
        except OSError as err:
            raise InputError(table, f"cannot read it ({err.strerror or err}); --pool takes the --out folders of "
                             "crossval runs") from None
        except (KeyError, ValueError) as err:
            raise InputError(table, f"not a crossval.csv ({err})") from None
        for r in found:
            j = r["fold"] if isinstance(r["fold"], int) else None
            if j is None:
                if not str(r["fold"]).startswith("pooled"):
                    rows.append(r)                                  # a "J:ID" row
                continue
            if j in source:
                raise InputError(table, f"fold {j} is in {source[j]} too; pool each fold once")
            if not 0 <= j < folds:
                raise InputError(table, f"fold {j} is not one of --folds {folds} (0..{folds - 1})")
            source[j] = table
            try:
                saved = read_checkpoint(d / f"fold{j}" / "last.pt")["config"]
            except Exception as exc:            # torch.load raises many kinds on a file that is not a checkpoint
                raise InputError(d / f"fold{j}" / "last.pt", f"not a usable fold checkpoint ({type(exc).__name__})"
                                 ", so its recipe cannot be checked") from None
            flat = _recipe(saved, free=("threads", "device"))     # the filter too: one recipe, one table
            if recipe is not None and flat != recipe[1]:
                k = sorted(k for k in flat.keys() | recipe[1].keys() if flat.get(k) != recipe[1].get(k))[0]
                raise InputError(table, f"fold {j} was trained with {k} = {flat.get(k, '(unset)')!r}, fold "
                                 f"{recipe[0]} with {recipe[1].get(k, '(unset)')!r}; pool runs of one recipe")
            recipe = recipe or (j, flat)
            started = started or (saved.get("train") or {}).get("init") or None
            rows.append(r)
    missing = [j for j in range(folds) if j not in source]
    if missing:
        raise ValueError(f"fold(s) {', '.join(map(str, missing))} of --folds {folds} are in none of the --pool "
                         "folders")
    rows.sort(key=lambda r: (int(str(r["fold"]).split(":")[0]), str(r["fold"])))
    datasets = list(dict.fromkeys(str(r["fold"]).split(":", 1)[1] for r in rows if ":" in str(r["fold"])))
    rows.extend(pooled_rows(rows, datasets))
    _make_out(out)
    _write_results(out, rows, command, started)
    return rows


def _csv_row(row: dict) -> dict:
    """A crossval.csv row as crossval made it: the fold an int where it is one, RMSEs and counts as numbers."""
    out = {k: row.get(k, "") for k in COLUMNS}
    out["fold"] = int(row["fold"]) if row["fold"].isdigit() else row["fold"]
    out["held_out_epochs"] = int(row["held_out_epochs"])
    # a crossval.csv from before session 54 has no labelled_epochs: its datasets were labelled at every epoch
    out["labelled_epochs"] = int(row.get("labelled_epochs") or row["held_out_epochs"])
    for k in COLUMNS:
        if k.endswith("_m"):
            out[k] = float(row[k]) if row[k] != "" else math.nan
    return out


def _made_by(command: str | None) -> str:
    """crossval.md's first lines: the command and the code it ran (``learning.provenance``), or nothing."""
    if command is None:
        return ""
    return f"Produced by `{command}` ({code_text(git_state())}).\n\n"


class UnwrittenResults(InputError):
    """crossval.csv or crossval.md could not be written (a full disk, a folder in the way); ``rows`` are the results."""

    def __init__(self, path: Path, err: OSError, rows: list[dict]) -> None:
        super().__init__(err.filename or path, cannot_write(err))
        self.rows = rows


def _start_note(init: str | None, rows: list[dict]) -> str:
    """crossval.md's line under the table when the folds started from ``init`` (train.init): its "untrained" column
    is that model, the one fine-tuning has to beat; "" otherwise (or when the column is empty, ``--reuse``)."""
    if not init or all(math.isnan(float(r["untrained_rmse_3d_m"])) for r in rows):
        return ""
    return (f"\nuntrained_rmse_3d_m is the starting model (train.init = {init}) before any training epoch: the "
            "one last_rmse_3d_m has to beat.\n")


def _write_results(out: Path, rows: list[dict], command: str | None = None, init: str | None = None) -> None:
    """``crossval.csv`` and ``crossval.md`` of ``rows`` in ``out`` (the .md headed by ``command`` and the code's git
    commit, and with ``init``, train.init, a note that "untrained" is that model); UnwrittenResults (with the rows)
    if one fails."""
    path = out / "crossval.csv"
    try:
        with open(path, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=COLUMNS)
            w.writeheader()
            w.writerows(rows)
        path = out / "crossval.md"
        path.write_text(_made_by(command) + markdown_table(rows, COLUMNS) + _start_note(init, rows))
    except OSError as err:
        raise UnwrittenResults(path, err, rows) from None


def _run_folds(rows: list[dict], chosen, folds: int, whole: dict, config: dict, out: Path, progress: bool,
               reuse, command: str | None = None, config_file: str | Path | None = None,
               epoch_lines: bool = False, combine: str = "geometric") -> None:
    """Train (or with ``reuse`` rescore) each chosen fold, appending its row to ``rows`` as soon as it is done."""
    data = config["data"]
    for j in chosen:
        parts = {}
        for ds, seqs in whole.items():
            try:
                parts[ds] = fold_sequences(seqs, folds, j)
            except ValueError as exc:
                raise ValueError(f"{ds}: {exc} (--folds {folds})") from None

        def source(ds: str, split: str, _config: dict, parts=parts) -> list[Sequence]:
            return parts[ds][0] if split == data["train_split"] else parts[ds][1]

        held = [s for _, h in parts.values() for s in h]
        pieces = [s for t, _ in parts.values() for s in t]
        if reuse is not None:
            saved = saved_ensemble(reuse, j, config, held, pieces)
            rows.append(_rescored_row(j, saved, config, held, combine))
            rows.extend(_dataset_rows(j, saved, config, parts, combine))
            continue
        if epoch_lines:                 # its epoch lines follow; their "val 3D RMSE" is on the held-out block
            print(f"fold {j} ({j + 1}/{folds}): training on {sum(map(len, pieces))} epochs in {len(pieces)} "
                  f"piece(s), holding out {sum(map(len, held))} epochs", flush=True)
        prep = prepare(config, source)
        history = train(copy.deepcopy(config), out / f"fold{j}", progress=progress, epoch_lines=epoch_lines,
                        prepared=prep, export=False,
                        command=command, config_file=config_file)
        best = min(history, key=lambda h: h["val_rmse_3d_m"])
        saved, last_smoothed_3d, last_2d = _saved_rmse_m(out / f"fold{j}" / "last.pt", config, prep)
        rows.append(_fold_row(j, held, config, {
            "untrained_rmse_3d_m": history[0]["val_rmse_3d_m"], "last_rmse_3d_m": history[-1]["val_rmse_3d_m"],
            "best_rmse_3d_m": best["val_rmse_3d_m"], "best_epoch": best["epoch"],
            "last_smoothed_rmse_3d_m": last_smoothed_3d, "last_rmse_2d_m": last_2d}))
        if len(parts) > 1:
            rows.extend(_dataset_rows(j, [saved], config, parts))


def _dataset_rows(fold: int, saved: list[dict], config: dict, parts: dict, combine: str = "geometric") -> list[dict]:
    """With several datasets, one row per dataset (fold ``"J:ID"``) of the fold's model on that dataset's held-out
    pieces (several models: their ensemble): a pooled row is dominated by the datasets with the most epochs, and can
    hide a loss on the others."""
    if len(parts) < 2:
        return []
    return [_rescored_row(f"{fold}:{ds}", saved, config, held, combine) for ds, (_, held) in parts.items() if held]


def _kept(exc: BaseException) -> str:
    """What a run stopped among its folds leaves behind, for its last line: the finished folds' rows (written by
    ``crossval``) and the folds' checkpoints."""
    stopped = getattr(exc, "crossval_stopped", None)
    if stopped is None:                 # stopped before the first fold: nothing of this run to keep
        return ""
    out, path, done = stopped
    note = f"; the rows of the finished fold(s) {', '.join(map(str, done))} are in {path}" if path else ""
    try:
        if any(out.glob("fold*/last.pt")):
            note += f"; the folds' checkpoints are kept in {out}"
    except OSError:
        pass
    return note


def _go_on(exc: BaseException, args: argparse.Namespace, command: str) -> str:
    """How a run stopped after some of its folds is finished (review: its --out refuses a second run, and nothing
    said so): the folds left as a --fold run of their own, then both pooled (``--pool``)."""
    stopped = getattr(exc, "crossval_stopped", None)
    if stopped is None or not stopped[2] or args.pool or args.reuse:
        return ""
    out, _, done = stopped
    left = [j for j in (sorted(set(args.only)) if args.only else range(args.folds)) if j not in done]
    if not left:
        return ""
    rest = Path(f"{out}-rest")
    again = re.sub(r"(^|\s)--(out|fold)(=|\s+)\S+", "", command).strip()
    return (f"; to finish, run the fold(s) left into a folder of their own ({again} "
            + " ".join(f"--fold {j}" for j in left) + f" --out {shlex.quote(str(rest))}), then pool the two "
            f"(python -m learning.crossval --folds {args.folds} --pool {shlex.quote(str(out))} --pool "
            f"{shlex.quote(str(rest))} --out {shlex.quote(str(out))}-all)")


def next_step(config_file: str | None, overrides: list[str]) -> str:
    """The line after a finished cross-validation: the command that trains the recipe it scored (its ``--set``s
    included) on the train split, selected on the validation split, as ``learning.train`` does."""
    recipe = ([] if config_file is None else ["--config", config_file]) + [a for o in overrides for a in ("--set", o)]
    return ("next: train this recipe on data.train_split (python -m learning.train "
            + " ".join(map(shlex.quote, [*recipe, "--out", "runs/NAME"])) + ")")


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point.

    Exit status 0; 2 for bad input (one line ``PROG: error: ...``, before any training where it can be seen then) or
    results that could not be written (printed all the same); 3 for a diverged fold or an internal error; 130 for
    Ctrl-C. A run that stops keeps its finished folds' rows in ``crossval.csv`` / ``crossval.md``.
    """
    p = argparse.ArgumentParser(prog="python -m learning.crossval", description=__doc__.split("\n")[0],
                                formatter_class=PlainHelp)
    p.add_argument("--config", type=config_path, help="TOML configuration: a file, or the name of a shipped one "
                   "(as learning.train's; default: built-in defaults)")
    p.add_argument("--folds", type=int, default=3, help="number of contiguous blocks (default 3)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a configuration key (repeatable)")
    p.add_argument("--fold", dest="only", type=int, action="append", metavar="J",
                   help="run only fold J (repeatable; no pooled row unless every fold runs): folds in parallel "
                        "processes, each with its own --out")
    p.add_argument("--reuse", metavar="DIR", type=path_option, action="append",
                   help="train nothing: score the saved fold models of an earlier run (its --out) again on their "
                        "held-out blocks under this run's [ekf] settings (--set ekf.KEY=VALUE); give that run's "
                        "--config, --folds and other --set's again (a run made before folds joined the train and "
                        "validation epochs is refused). Repeated: the ensemble of several runs' fold models (runs "
                        "that differ in --set seed=S only)")
    p.add_argument("--combine", choices=COMBINE_RULES, default=COMBINE_RULES[0],
                   help="with several --reuse: how the ensemble's members are combined (learning.network."
                        "combine_members): geometric mean of R (default, as model files do) or their moment-matched "
                        "Gaussian mixture (mean R plus the spread of v^c)")
    p.add_argument("--pool", metavar="DIR", type=path_option, action="append",
                   help="train and score nothing: put the folds of parallel --fold runs (their --out folders, "
                        "repeat --pool) in one table with the pooled rows, written to --out")
    p.add_argument("--out", type=path_option, help="output folder (default: runs/cv-<config name>)")
    p.add_argument("--no-progress", action="store_true",
                   help="no progress bars (the fold and epoch lines are printed all the same)")
    args = p.parse_args(argv)
    if args.pool and (args.reuse or args.only or args.config or args.overrides or not args.out
                      or args.combine != COMBINE_RULES[0]):
        p.error("--pool takes only --folds and an --out of its own (the recipe is the runs' own)")
    out = Path(args.out or Path("runs") / f"cv-{Path(args.config).stem if args.config else 'default'}")
    command = command_line(p.prog, sys.argv[1:] if argv is None else list(argv))
    try:
        with warnings_on_one_line():
            if args.pool:
                pool(args.pool, args.folds, out, command)
            else:
                config = load_config(args.config, args.overrides)
                crossval(config, args.folds, out, progress=not args.no_progress, only=args.only, reuse=args.reuse,
                         command=command, config_file=args.config, epoch_lines=True, combine=args.combine)
    except UnwrittenResults as exc:           # computed, not written: the table goes to stdout all the same
        print(markdown_table(exc.rows, COLUMNS), end="")
        exit_on_input_error(p, exc)
    except (*INPUT_ERRORS, OSError) as exc:
        p.exit(2, f"{p.prog}: error: {input_line(exc)}{_kept(exc)}\n")
    except FloatingPointError as exc:         # a fold diverged: not bad input (exit 3, as learning.train)
        p.exit(3, f"{p.prog}: error: {one_line(exc)}: cross-validation stopped (exit status 3){_kept(exc)}; "
                  "check [loss], or try a lower train.lr or a train.grad_clip > 0\n")
    except KeyboardInterrupt as exc:
        p.exit(130, f"{p.prog}: interrupted{_kept(exc)}{_go_on(exc, args, command)}\n")
    except Exception as exc:  # a bug, not bad input: still one line, no traceback, a distinct exit code
        p.exit(3, f"{p.prog}: error: internal error ({type(exc).__name__}: {one_line(exc)}){_kept(exc)}; "
                  "please report it\n")
    print_stdout((out / "crossval.md").read_text(), end="")   # a reader gone (| head): the results are written
    if not (args.pool or args.reuse or args.only):
        print_stdout(next_step(args.config, args.overrides))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
