"""Train the LF-GNSS noise network end to end through the differentiable EKF.

    python -m learning.train --config learning/configs/default.toml [--set key=value ...]
                             [--out runs/NAME] [--resume] [--no-progress]

Each epoch: shuffled windows of consecutive epochs -> network -> ``learning.torch_ekf.batch_ekf``
-> HEM (or RMSE) loss on the filtered positions -> Adam (AdamW if ``train.weight_decay`` > 0); then the torch EKF runs over each whole
validation sequence (no gradient) for the validation 3D RMSE. Every epoch writes ``last.pt``
(model, optimiser, scheduler, epoch, RNG states, normaliser, config); the best validation epoch
is kept as ``best.pt`` and exported to ``model.npz`` (``train.select = "last"`` exports the last epoch
instead: a fixed schedule, e.g. one chosen by ``learning.crossval``); ``log.csv`` and ``curves.png`` record the run.
With ``train.ema_decay`` = d > 0 the validated, saved and exported weights are an exponential moving
average of the end-of-epoch weights, ``w_avg = d w_avg + (1 - d) w`` (``torch.optim.swa_utils``), which
steadies a fixed schedule's last epoch; training itself goes on from the raw weights.
With ``train.init`` = a model file (``.npz``, or a bundled model's name: ``"default"`` is the shipped one),
training starts from that model's weights instead of random ones (fine-tuning on your own data): the network, its
features and their normalisation are the model's, so ``[model]`` and ``data.features``/``data.drop_features`` are
taken from the file, and so is its filter (``[ekf]``) except for the keys the configuration sets; the new model
file records the one it started from (``init_model``: path, hash, and the data it was trained on).
The test split is never loaded here: asking for it raises.
``device`` = "cuda" (or "auto") trains on a GPU; it pays off only with large batches (docs/training_speed.md).
``--resume`` goes on from ``last.pt`` with the run's own configuration (the one the model file will record): only
``--set train.epochs=N`` (to extend the schedule), ``threads`` and ``device`` may change (``RESUME_FREE``); any other
``--set`` that differs from the checkpoint's is refused, and so is a ``--config`` other than the unchanged file the run
was started from. Every file is written to a temporary file and renamed (atomic): a kill mid-write keeps the last one.
Exit status: 0 done; 2 bad input (a one-line error naming the file or setting; nothing is written for a bad
setting); 3 the training loss or its gradient became non-finite (one line; ``last.pt``/``best.pt`` of the epochs
before are kept); 130 Ctrl-C (one line naming the epoch ``last.pt`` holds and the ``--resume`` command that goes on).
Output: one line per epoch on stdout (epoch 0 is the starting model, untrained or ``train.init``'s: the one training
has to beat), ``--no-progress`` or not; a progress bar on stderr only where it is a terminal; last, the best epoch,
the model file and how to use it. ``--resume`` of a run already at ``train.epochs`` says so (and trains nothing).

Sequences come from one pluggable function, ``load_sequences(dataset_id, split, config)``:
dataset ``"synthetic"`` uses ``lfgnss.simulate.simulate_sequence``, any other id goes to
``lfgnss.datasets.load_split``; your own data is a dataset TOML file (``lfgnss.datasets.register_toml``)
named in ``data.register``, e.g. ``--set 'data.register=["my-drive.toml"]' --set 'data.datasets=["my-drive"]'``.
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import csv
import dataclasses
import hashlib
import importlib
import math
import os
import pickle
import random
import re
import shlex
import sys
import time
import warnings
import tomllib
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch

from lfgnss.datasets import get, load_split, register_toml, split_parts
from lfgnss.errors import INPUT_ERRORS, did_you_mean, one_line, path_option, shortened, warnings_on_one_line
from lfgnss.help_text import PlainHelp
from lfgnss.paths import (check_output_folder, file_hash, file_hashes, may_name_a_bundled_model, names_something,
                          replace_atomically)
from lfgnss.sequence import DEFAULT_FEATURES, Sequence

from . import provenance
from .data import Window, collate, make_windows, resolve_feature_names, sequence_batch, signed_log_names
from .export import MIN_R_FLOOR_M2, model_settings, truth_extent
from .loss import compensation_loss, error_norm_m, labelled_errors_m, make_loss, variance_loss
from .network import LfgnssNet
from .normalise import Normaliser
from .types import WindowBatch

#: Every configuration key with its default; a TOML file overrides any subset.
DEFAULT_CONFIG: dict[str, Any] = {
    "seed": 0,
    "threads": 1,
    "device": "cpu",
    "data": {
        "datasets": ["hk-tst-2019"],
        "train_split": "train",
        "val_split": "val",
        "features": list(DEFAULT_FEATURES),
        "drop_features": [],
        "signed_log": [],
        "register": [],
        "window": 40,
        "stride": 5,
        "burn_in": 0,
        "synthetic": {"n_epochs": 300, "sats_per_system": 7, "systems": ["G", "C"], "nlos_fraction": 0.2,
                      "train_seeds": [1, 2], "val_seeds": [101]},
    },
    "model": {"d_model": 64, "n_heads": 4, "hidden": [64, 128, 64], "r_floor_m2": 0.01, "r_scale_m2": 1.0,
              "r_init_m2": None, "r_prior": "none", "compensation": True, "innovation": False},
    "train": {"epochs": 200, "batch_size": 16, "lr": 1.0e-3, "t_max": 50, "eta_min": 1.0e-4, "grad_clip": 0.0,
              "feature_noise": 0.0, "weight_decay": 0.0, "select": "val", "ema_decay": 0.0, "init": "", "smooth": False,
              "freeze": []},
    "loss": {"kind": "hem", "alpha": 0.75, "gamma": 1.5, "lambda": 1.0, "up_weight": 1.0, "balance": "none",
             "vc_weight": 0.0, "vc_delta_m": 5.0, "r_weight": 0.0, "r_clock": "median"},
    "ekf": {},
}

_FORBIDDEN_SPLITS = ("test",)

#: What an unknown dataset id's error adds here: training and cross-validation take a dataset of one's own as a
#: setting (recorded in the run and checked on --resume), not as a --register option.
REGISTER_HINT = ("register a dataset of your own first: --set 'data.register=[\"FILE.toml\"]' --set "
                 "'data.datasets=[\"ID\"]', or data.register = [\"FILE.toml\"] in the training config")

#: The network's parts by name (``learning.network.LfgnssNet``), for ``train.freeze``: these keep their initial
#: (``train.init``) weights while the rest is trained.
NETWORK_PARTS = ("embed", "attention", "norm", "mlp", "head")

#: Settings ``--resume`` may change: how far the schedule runs, and how the run uses the machine. Every other one is
#: the checkpoint's (the saved optimiser and scheduler fix train.lr, weight_decay, t_max and eta_min; the rest would
#: make the model file say the whole run used what only its later epochs did).
RESUME_FREE = ("train.epochs", "threads", "device")
_RESUME_RULE = ("a resumed run goes on with the configuration it was started with: only --set train.epochs=N "
                "(to extend the schedule), threads and device may change")


# --------------------------------------------------------------------------- configuration

def _flat(table: dict, prefix: str = "") -> dict:
    """Nested tables as one dict of dotted keys, e.g. ``{"train.epochs": 200}``."""
    out = {}
    for key, value in table.items():
        if isinstance(value, dict):
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _merge(base: dict, update: dict, where: str = "") -> dict:
    out = copy.deepcopy(base)
    for key, value in update.items():
        if key not in out and where != "ekf." and not where.startswith("ekf."):
            known = list(_flat(DEFAULT_CONFIG)) + ["data", "data.synthetic", "model", "train", "loss", "ekf"]
            raise ValueError(f"unknown configuration key {where + key!r}{did_you_mean(where + key, known)}")
        if isinstance(out.get(key), dict) and not isinstance(value, dict):    # ekf = 3, --set data=1
            raise ValueError(f"{where + key} must be a table of settings, got {value!r}")
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value, where + key + ".")
        else:
            out[key] = copy.deepcopy(value)
    return out


def _parse_value(text: str) -> Any:
    """A TOML literal (number, bool, string, array); a bare word falls back to a string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


def apply_overrides(config: dict, assignments: list[str]) -> dict:
    """``["train.epochs=5", "loss.kind=rmse"]`` applied to ``config`` (dotted keys, TOML values)."""
    out = copy.deepcopy(config)
    for item in assignments:
        if "=" not in item:
            raise ValueError(f"--set expects key=value, got {item!r}")
        key, text = item.split("=", 1)
        *parents, leaf = key.strip().split(".")
        nested: dict = {}
        cursor = nested
        for p in parents:
            cursor = cursor.setdefault(p, {})
        cursor[leaf] = _parse_value(text.strip())
        out = _merge(out, nested)
    return out


#: The training configurations shipped with lfgnss (``--config NAME`` picks ``NAME.toml`` here).
CONFIG_DIR = Path(__file__).resolve().parent / "configs"


def shipped_configs() -> list[str]:
    """The names of the shipped training configurations: ``default``, ``finetune``, ``berlin``, ..."""
    return sorted(p.stem for p in CONFIG_DIR.glob("*.toml"))


def shipped_config(name: str) -> Path | None:
    """The shipped configuration called ``name`` (``finetune`` or ``finetune.toml``: learning/configs/finetune.toml;
    a shipped file copied elsewhere keeps its ``base = "default.toml"``), or None where ``name`` has a folder or
    another suffix or no shipped file has that name."""
    stem = name.removesuffix(".toml")
    shipped = CONFIG_DIR / f"{stem}.toml"
    return shipped if may_name_a_bundled_model(stem) and shipped.is_file() else None


def config_path(config: str) -> str:
    """``--config``: a path as given where it names a file, else the shipped configuration of that name
    (:func:`shipped_config`), else as given (its reader names what is missing)."""
    shipped = None if Path(config).is_file() else shipped_config(config)   # a folder of that name hides nothing
    return config if shipped is None else str(shipped)


def load_config(path: str | Path | None = None, overrides: list[str] = ()) -> dict:
    """DEFAULT_CONFIG updated by the TOML file at ``path`` and then by ``overrides``.

    ValueError for a wrong setting (``check_config``); one that the file itself gets wrong names the file.
    """
    config = copy.deepcopy(DEFAULT_CONFIG)
    if path is not None:
        path = config_path(str(path))                 # "finetune": the shipped configuration of that name
        data = _read_toml(Path(path))                 # its own errors name the file
        try:
            config = _merge(config, data)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
    try:
        return check_config(apply_overrides(config, list(overrides)))
    except ValueError as exc:
        if path is not None:
            try:
                check_config(copy.deepcopy(config))
            except ValueError as alone:              # the same error without the --set overrides: the file's
                if str(alone) == str(exc):
                    raise ValueError(f"{path}: {exc}") from None
        raise


def resolve_device(name: object) -> torch.device:
    """The torch device of the ``device`` setting: "cpu", "cuda", "cuda:N", or "auto" (CUDA when there is one)."""
    if not isinstance(name, str) or not (name in ("cpu", "cuda", "auto") or
                                         (name.startswith("cuda:") and name[5:].isdigit())):
        raise ValueError(f"device must be 'cpu', 'cuda', 'cuda:N' or 'auto', got {name!r}")
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device = {name!r}: this torch ({torch.__version__}) sees no CUDA GPU; "
                             "use device = 'cpu' or 'auto'")
        if (device.index or 0) >= torch.cuda.device_count():
            raise ValueError(f"device = {name!r}: only {torch.cuda.device_count()} CUDA GPU(s) here")
    return device


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run the block on ``n`` CPU threads (the ``threads`` setting), then give back the previous number."""
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def _setting(config: dict, key: str) -> Any:
    """The dotted ``key`` of ``config``, or its default where the table lacks it (runs from before the key resume)."""
    value, default = config, DEFAULT_CONFIG
    for part in key.split("."):
        default = default[part]
        value = value.get(part, default)
    return value


def _check_number(config: dict, key: str, low: float, high: float = math.inf, *, whole: bool = False,
                  above: bool = False) -> None:
    """ValueError naming ``key`` unless it is a finite number (an int with ``whole``; never a bool) in [low, high]
    (``above``: in (low, high])."""
    value = _setting(config, key)
    if not (not isinstance(value, bool) and isinstance(value, int if whole else (int, float))
            and (isinstance(value, int) or math.isfinite(value)) and (value > low if above else value >= low)
            and value <= high):
        bounds = f"{'>' if above else '>='} {low}" + (f" and <= {high}" if high < math.inf else "")
        raise ValueError(f"{key} must be {'a whole number' if whole else 'a finite number'} {bounds}, got {value!r}")


def check_config(config: dict) -> dict:
    """``config``, or ValueError naming a setting of the wrong kind (caught before any data loads).

    A single string where a list of names is expected (``--set data.datasets=synthetic``) becomes a one-item list.
    """
    for key in ("data", "data.synthetic", "model", "train", "loss", "ekf"):
        if not isinstance(_setting(config, key), dict):
            raise ValueError(f"{key} must be a table of settings, got {_setting(config, key)!r}")
    resolve_device(config.get("device", "cpu"))
    for key, what in (("datasets", "dataset ids"), ("features", "feature names"),
                      ("drop_features", "feature names (or 'dpc')"), ("signed_log", "feature names (or 'dpc')"),
                      ("register", "dataset TOML files")):
        items = _setting(config, f"data.{key}")
        if isinstance(items, str):                        # --set data.register=my.toml: one file, not its letters
            config["data"][key] = items = [items]
        needed = key in ("datasets", "features")
        if not isinstance(items, list) or not all(isinstance(i, str) for i in items) or (needed and not items):
            raise ValueError(f"data.{key} must be a {'non-empty ' * needed}list of {what}, got {items!r}")
    names = resolve_feature_names(_setting(config, "data.features"), _setting(config, "data.drop_features"))  # typos
    signed_log_names(_setting(config, "data.signed_log"), names, _setting(config, "model.r_prior"))
    datasets = _setting(config, "data.datasets")
    twice = sorted({d for d in datasets if datasets.count(d) > 1})
    if twice:                                             # each would be loaded, trained on and validated on twice
        raise ValueError(f"data.datasets names {', '.join(map(repr, twice))} more than once (its data would count "
                         f"twice); name each dataset once, got {datasets!r}")
    for key, what in (("data.train_split", "a split name or names joined by '+'"),
                      ("data.val_split", "a split name or names joined by '+'"),
                      ("train.init", "the path of a model file or a bundled model's name")):
        if not isinstance(_setting(config, key), str):
            raise ValueError(f"{key} must be {what} (a string), got {_setting(config, key)!r}")
    for key in ("data.train_split", "data.val_split"):
        parts = split_parts(_setting(config, key))
        if any(not part or part != part.strip() for part in parts) or len(set(parts)) < len(parts):
            raise ValueError(f"{key} must be a split name or names joined by '+' (e.g. \"train+val\"), each once and "
                             f"without spaces, got {_setting(config, key)!r}")
    for key, choices in (("train.select", ("val", "last")), ("model.r_prior", ("none", "heuristic")),
                         ("loss.kind", ("hem", "rmse")), ("loss.balance", ("none", "plain_ekf")),
                         ("loss.r_clock", ("median", "strongest"))):
        if _setting(config, key) not in choices:
            raise ValueError(f"{key} must be {' or '.join(map(repr, choices))}, got {_setting(config, key)!r}")
    for key in ("train.smooth", "model.compensation", "model.innovation"):
        if not isinstance(_setting(config, key), bool):
            raise ValueError(f"{key} must be true or false, got {_setting(config, key)!r}")
    _check_number(config, "seed", 0, 2**32 - 1, whole=True)
    for key in ("threads", "data.window", "data.stride", "data.synthetic.n_epochs", "data.synthetic.sats_per_system",
                "model.d_model", "model.n_heads", "train.epochs", "train.batch_size", "train.t_max"):
        _check_number(config, key, 1, whole=True)
    for key, above in (("train.lr", False), ("train.eta_min", False), ("train.weight_decay", False),
                       ("train.grad_clip", False), ("train.feature_noise", False), ("model.r_scale_m2", True),
                       ("loss.alpha", True), ("loss.gamma", False),
                       ("loss.lambda", False), ("loss.up_weight", False), ("loss.vc_weight", False),
                       ("loss.vc_delta_m", True), ("loss.r_weight", False)):
        _check_number(config, key, 0, above=above)
    if _setting(config, "loss.vc_weight") > 0 and _setting(config, "model.innovation"):
        raise ValueError("loss.vc_weight needs a network that reads its features alone; with model.innovation = true "
                         "its v^c is made inside the filter")
    if _setting(config, "loss.r_weight") > 0 and _setting(config, "model.innovation"):
        raise ValueError("loss.r_weight needs a network that reads its features alone; with model.innovation = true "
                         "its R is made inside the filter")
    _check_number(config, "model.r_floor_m2", MIN_R_FLOOR_M2)
    if _setting(config, "loss.vc_weight") > 0 and not _setting(config, "model.compensation"):
        raise ValueError("loss.vc_weight supervises v^c, and model.compensation = false has none (v^c = 0)")
    _check_number(config, "data.synthetic.nlos_fraction", 0, 1)
    if _setting(config, "model.r_init_m2") is not None:
        _check_number(config, "model.r_init_m2", 0, above=True)
    if _setting(config, "model.r_prior") == "heuristic":
        # r = prior * softplus(o_R) / ln 2 + floor: no unit scale, and an untrained network already gives the prior
        if _setting(config, "model.r_init_m2") is not None:
            raise ValueError("model.r_init_m2 has no meaning with model.r_prior = 'heuristic' (an untrained network "
                             "gives about the C/N0-elevation prior); leave it out")
        if _setting(config, "model.r_scale_m2") != 1.0:
            raise ValueError(f"model.r_scale_m2 = {_setting(config, 'model.r_scale_m2')!r} is not read with "
                             f"model.r_prior = 'heuristic' (R is a factor on the prior); leave it at 1.0")
    frozen = _setting(config, "train.freeze")
    if isinstance(frozen, str):
        config["train"]["freeze"] = frozen = [frozen]
    if not isinstance(frozen, list) or not all(isinstance(f, str) and f in NETWORK_PARTS for f in frozen):
        raise ValueError(f"train.freeze must be a list of network parts ({', '.join(NETWORK_PARTS)}), got {frozen!r}")
    for key, low in (("model.hidden", 1), ("data.synthetic.train_seeds", 0), ("data.synthetic.val_seeds", 0)):
        items = _setting(config, key)
        if not isinstance(items, list) or not all(type(i) is int and i >= low for i in items):
            raise ValueError(f"{key} must be a list of whole numbers >= {low}, got {items!r}")
    d_model, n_heads = _setting(config, "model.d_model"), _setting(config, "model.n_heads")
    if d_model % n_heads:
        raise ValueError(f"model.d_model must be a multiple of model.n_heads ({n_heads}), got {d_model}")
    ema = _setting(config, "train.ema_decay")
    if isinstance(ema, bool) or not isinstance(ema, (int, float)) or not 0.0 <= ema < 1.0:
        raise ValueError(f"train.ema_decay must be a number in [0, 1), got {ema!r}")
    burn_in, window = _setting(config, "data.burn_in"), _setting(config, "data.window")
    if isinstance(burn_in, bool) or not isinstance(burn_in, int) or not 0 <= burn_in < window:
        raise ValueError(f"data.burn_in must be a whole number of epochs >= 0 and below data.window ({window}), "
                         f"got {burn_in!r}")
    for key, value in _setting(config, "ekf").items():    # every EkfConfig field is a number
        if isinstance(value, bool) or not isinstance(value, (int, float)) or math.isnan(value):
            raise ValueError(f"ekf.{key} must be a number, got {value!r}")
    ekf_config(config)                                    # unknown [ekf] keys, or values EkfConfig refuses
    return config


def _files_absolute(config: dict) -> dict:
    """``config`` with its files (``data.register``, a ``train.init`` path) absolute where they name one from the
    current folder, so that the run's checkpoints and model file (``--resume``, ``learning.export --show --config``)
    reproduce it from any folder; a bundled model's name stays one."""
    def absolute(path: str) -> str:
        return str(Path(path).resolve()) if path and names_something(path) else path

    init = config["train"]["init"]
    return {**config, "data": {**config["data"], "register": [absolute(p) for p in config["data"]["register"]]},
            "train": {**config["train"], "init": init if may_name_a_bundled_model(init) else absolute(init)}}


def _beside(path: Path, name: object) -> object:
    """``name`` read next to the configuration file ``path`` when it is a relative path found there, else as given."""
    if isinstance(name, str) and name and not Path(name).is_absolute() and names_something(path.parent / name):
        return str(path.parent / name)
    return name


def _dataset_toml(path: Path, name: object) -> object:
    """A ``data.register`` entry of the configuration file ``path``: found beside it, else in the current folder
    (InputError listing both places when in neither); a non-path is left for the type check."""
    from lfgnss.datasets import find_dataset_toml

    return str(find_dataset_toml(name, (path.parent,))) if isinstance(name, str) and name else name


def _read_toml(path: Path, depth: int = 0) -> dict:
    """A TOML file; a top-level ``base = "other.toml"`` (relative to it) is read first and updated.

    Like ``base``, the relative files it names (``data.register``, ``train.init``) are looked for next to it
    first, then in the current folder; a ``train.init`` found in neither that has no folder or suffix is a bundled
    model's name (``lfgnss.paths.model_path``: the shipped fine-tuning configurations name theirs so).
    """
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        stem = str(path).removesuffix(".toml")
        if not may_name_a_bundled_model(stem):
            raise ValueError(f"{path}: cannot read configuration: no such file") from None
        hint = did_you_mean(stem, shipped_configs()) or f" (shipped: {', '.join(shipped_configs())})"
        raise ValueError(f"{path}: cannot read configuration: no such file, nor a shipped configuration of that name"
                         f"{hint}") from None
    except (OSError, ValueError, RecursionError) as exc:   # ValueError: TOMLDecodeError, or bytes that are not UTF-8
        raise ValueError(f"{path}: cannot read configuration: {one_line(exc)}") from None
    for key, value in data.items():
        if isinstance(DEFAULT_CONFIG.get(key), dict) and not isinstance(value, dict):
            raise ValueError(f"{path}: {key} must be a table of settings ([{key}]), got {value!r}")
    section = data.get("data", {})
    if isinstance(section.get("register"), list):
        section["register"] = [_dataset_toml(path, r) for r in section["register"]]
    elif "register" in section:
        section["register"] = _dataset_toml(path, section["register"])
    if "init" in data.get("train", {}):
        data["train"]["init"] = _beside(path, data["train"]["init"])
    base = data.pop("base", None)
    if base is None:
        return data
    if not isinstance(base, str):
        raise ValueError(f"{path}: base must be the path of a configuration file (a string), got {base!r}")
    if depth > 8:
        raise ValueError(f"{path}: 'base' chain too deep")
    beside = path.parent / base
    found = beside if beside.is_file() else shipped_config(base)      # base = "finetune": the shipped one of that name
    if found is None:
        raise ValueError(f"{path}: base = {base!r}: no such configuration file beside it ({beside}), nor a shipped "
                         f"one of that name ({', '.join(shipped_configs())})")
    return _merge_free(_read_toml(found, depth + 1), data)


def _merge_free(base: dict, update: dict) -> dict:
    out = copy.deepcopy(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge_free(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def ekf_config(config: dict):
    """``estimators.models.EkfConfig`` with the ``[ekf]`` overrides applied."""
    from estimators.models import EkfConfig

    known = {f.name for f in dataclasses.fields(EkfConfig)}
    unknown = sorted(set(config["ekf"]) - known)
    if unknown:
        hint = did_you_mean(f"ekf.{unknown[0]}", [f"ekf.{k}" for k in sorted(known)])
        raise ValueError(f"unknown [ekf] keys {unknown}{hint}; EkfConfig has {sorted(known)}")
    try:
        return EkfConfig(**config["ekf"])
    except ValueError as err:                # "estimators/models.py: EkfConfig.KEY ...": name the setting instead
        raise ValueError(str(err).replace("estimators/models.py: EkfConfig.", "ekf.")) from None


def init_saw_validation(init, config: dict) -> list[str]:
    """Where the model fine-tuning starts from (``init``) was trained or selected on epochs of the run's validation
    split: its own pieces of a split of that name of the same dataset, or the same drive under another dataset id
    or file (``learning.crossval._init_saw_blocks``); the first line per dataset."""
    from .crossval import _init_saw_blocks
    from .export import _select, _used_as

    data = config["data"]
    wanted = set(split_parts(data["val_split"]))
    lines, others = [], {}
    for ds in data["datasets"]:
        pieces = sorted({str(p.get("split")) for p in init.metadata.get("data_fingerprints") or []
                         if isinstance(p, dict) and p.get("dataset") == ds and set(split_parts(str(p.get("split"))))
                         & wanted})
        if pieces:
            lines.append(f"{_used_as(pieces[0], _select(init.metadata))} {ds} {pieces[0]}")
        elif ds != "synthetic":
            others[ds] = load_sequences(ds, data["val_split"], config)
    return lines + _init_saw_blocks(init, others, "validation epochs")


def init_model(config: dict):
    """The ``train.init`` model file (``learning.export.LfgnssModel``), or None when training starts from scratch."""
    path = config["train"].get("init", "")
    if not path:
        return None
    from .export import load_model

    model = load_model(path)
    if len(model.members) > 1:
        raise ValueError(f"train.init: {model.path} is an ensemble of {len(model.members)} networks; fine-tuning "
                         "starts from one network: export one member's checkpoint (python -m learning.export "
                         "CHECKPOINT OUT.npz) and give that")
    return model


def adopt_init(config: dict) -> dict:
    """A copy of ``config`` whose network, features and filter are those the ``train.init`` model was trained with.

    Fine-tuning keeps the network and the meaning of its inputs, so these come from the model file; a note
    on stderr says when the given configuration asked for something else. The filter (``[ekf]``) is the model's
    too, except for the keys the configuration sets itself: a model fine-tuned in another filter would learn,
    and then run, in that filter (a note lists what is taken from the model).
    """
    model = init_model(config)
    if model is None:
        return config
    trained = model.metadata.get("config") or {}
    if "model" not in trained:
        raise ValueError(f"train.init: {model.path} does not record its training configuration")
    out = copy.deepcopy(config)
    out["model"] = copy.deepcopy(trained["model"])
    out["data"]["features"] = list(model.feature_names)
    out["data"]["drop_features"] = []
    out["data"]["signed_log"] = list(model.normaliser.signed_log)
    given = resolve_feature_names(config["data"]["features"], config["data"]["drop_features"])
    logged = signed_log_names(config["data"]["signed_log"], given)
    if (config["model"] != out["model"] or tuple(given) != model.feature_names
            or set(logged) != set(model.normaliser.signed_log)):
        print(f"train.init: the network and features are those of {model.path} ([model], data.features and "
              "data.signed_log of the configuration are replaced)", file=sys.stderr)
    adopted = {k: v for k, v in _own_filter(model).items() if k not in config["ekf"]}
    out["ekf"] = {**adopted, **config["ekf"]}
    if adopted:
        print(f"train.init: fine-tuned in the filter {model.path} runs in: "
              f"{', '.join(f'ekf.{k} = {v}' for k, v in adopted.items())} (an [ekf] key of the configuration "
              "overrides it)", file=sys.stderr)
    return out


def _own_filter(model) -> dict:
    """The ``EkfConfig`` fields in which a model file's filter differs from the defaults."""
    from estimators.ekf import config_of
    from estimators.models import EkfConfig

    default = dataclasses.asdict(EkfConfig())
    return {k: v for k, v in dataclasses.asdict(config_of(model)).items() if default[k] != v}


def trained_datasets(model) -> list[str]:
    """Dataset ids a loaded model file was trained on (its recorded ``data.datasets``)."""
    return list(((model.metadata.get("config") or {}).get("data") or {}).get("datasets", []))


def init_record(model) -> dict:
    """What a fine-tuned model file says about the model it started from: path, content hash and lineage."""
    meta = model.metadata
    return {"path": str(model.path), "sha256_16": file_hash(model.path, content=False), "epoch": meta.get("epoch"),
            "datasets": trained_datasets(model),
            "train_split": (meta.get("config") or {}).get("data", {}).get("train_split", "train"),
            "select": ((meta.get("config") or {}).get("train") or {}).get("select", "val"),
            "data_fingerprints": meta.get("data_fingerprints", []), "data_spans": meta.get("data_spans", []),
            "source_files": meta.get("source_files", {}), "init_model": meta.get("init_model")}


# --------------------------------------------------------------------------- data source

def load_sequences(dataset_id: str, split: str, config: dict) -> list[Sequence]:
    """The one place Sequences come from: synthetic, or ``lfgnss.datasets.load_split``.

    ``split`` may join names with "+" (``"train+val"``: both splits' epochs). Raises ValueError for the test split
    (training must never see it).
    """
    if set(split_parts(split)) & set(_FORBIDDEN_SPLITS):
        raise ValueError(f"training asked for split {split!r} of {dataset_id!r}; the test split is never used here")
    if dataset_id == "synthetic":
        from lfgnss.simulate import simulate_sequence

        syn = config["data"]["synthetic"]
        missing = [part for part in split_parts(split) if syn.get(f"{part}_seeds") is None]
        if missing:
            raise ValueError(f"synthetic data has no seeds for split {missing[0]!r} "
                             f"(data.synthetic.{missing[0]}_seeds)")
        return [simulate_sequence(int(syn["n_epochs"]), systems=tuple(syn["systems"]),
                                  sats_per_system=int(syn["sats_per_system"]),
                                  nlos_fraction=float(syn["nlos_fraction"]), seed=int(s),
                                  name=f"synthetic/{part}/{s}")
                for part in split_parts(split) for s in syn[f"{part}_seeds"]]

    for path in config["data"].get("register", []):        # the user's own datasets, by TOML file
        register_toml(path)
    get(dataset_id, hint=REGISTER_HINT)                     # unknown: how these commands register one
    pieces = list(load_split(dataset_id, split, feature_names=tuple(config["data"]["features"])))
    _refuse_far_truth(dataset_id, split, pieces)
    return pieces


def _refuse_far_truth(dataset_id: str, split: str, pieces: list[Sequence]) -> None:
    """ValueError where the truth lies a median beyond ``TRUTH_MISMATCH_M`` from the coarse fixes: a truth of
    another drive, in radians, or shifted in time would teach the network wrong labels (building it warns why)."""
    from lfgnss.datasets import TRUTH_MISMATCH_M, median_truth_gap_m

    if not pieces:
        return
    gap_m, n = median_truth_gap_m(np.concatenate([s.truth_ecef_m for s in pieces]),
                                  np.concatenate([s.coarse_ecef_m for s in pieces]))
    if gap_m > TRUTH_MISMATCH_M:
        raise ValueError(f"{dataset_id}/{split}: the truth lies a median {gap_m / 1000:.1f} km from the receiver's "
                         f"coarse fixes ({n} epochs), so training would learn from wrong labels; mend the truth file "
                         f"first (python -m lfgnss.datasets --register ... says what looks wrong)")


def source_file_hashes(dataset_id: str) -> dict[str, str]:
    """sha256 (16 hex digits) of each input file of a benchmark dataset; {} for synthetic data."""
    if dataset_id == "synthetic":
        return {}
    from lfgnss.datasets import get

    return file_hashes(get(dataset_id).files())


def data_span(dataset_id: str, split: str, sequence: Sequence) -> dict:
    """A sequence's dataset, split, name, constellations (letters), first and last GPS time [s] and truth's extent
    (``truth_extent``) [m]."""
    t = sequence.time_gps_s
    centre, radius = truth_extent(sequence.truth_ecef_m[sequence.labelled])
    return {"dataset": dataset_id, "split": split, "sequence": sequence.name, "systems": "".join(sequence.systems),
            "gps_s": [float(t[0]), float(t[-1])] if len(t) else [],
            "place_ecef_m": [round(float(v)) for v in centre] if radius is not None else [],
            "radius_m": math.ceil(radius) if radius is not None else None}


def fingerprint(sequence: Sequence) -> str:
    """sha256 (16 hex digits) of a sequence's measurements, features and truth."""
    h = hashlib.sha256()
    for arr in (sequence.time_gps_s, sequence.mask, sequence.pr_m, sequence.features, sequence.truth_ecef_m):
        h.update(np.ascontiguousarray(arr).tobytes())
    return h.hexdigest()[:16]


# --------------------------------------------------------------------------- model / evaluation

def build_model(config: dict, n_features: int, normaliser: Normaliser | None = None) -> LfgnssNet:
    """LfgnssNet from the ``[model]`` table (``r_prior = "heuristic"`` needs the normaliser)."""
    from .network import heuristic_prior

    m = config["model"]
    prior = None
    if m.get("r_prior", "none") == "heuristic":
        if normaliser is None:
            raise ValueError("model.r_prior = 'heuristic' needs the fitted normaliser")
        prior = heuristic_prior(normaliser.feature_names, normaliser.mean, normaliser.std)
    elif m.get("r_prior", "none") != "none":
        raise ValueError(f"model.r_prior must be 'none' or 'heuristic', got {m['r_prior']!r}")
    return LfgnssNet(n_features, d_model=int(m["d_model"]), n_heads=int(m["n_heads"]), hidden=tuple(m["hidden"]),
                     r_floor_m2=float(m["r_floor_m2"]), r_scale_m2=float(m["r_scale_m2"]),
                     r_init_m2=None if m.get("r_init_m2") is None else float(m["r_init_m2"]), r_prior=prior,
                     compensation=bool(m.get("compensation", True)), innovation=bool(m.get("innovation", False)))


def checkpoint_network(saved: dict) -> tuple[LfgnssNet, Normaliser]:
    """A read checkpoint's network with its saved weights, and the normaliser of its features."""
    normaliser = Normaliser.from_dict(saved["normaliser"])
    model = build_model(saved["config"], len(normaliser.feature_names), normaliser)
    model.load_state_dict(saved["model"])
    return model, normaliser


def run_filter(model: LfgnssNet, batch: WindowBatch, *, n_systems: int, ekf_cfg, smooth: bool = False,
               noise: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """Filtered (or, with ``smooth``, RTS-smoothed) positions (B, T, 3) [m] with the network's R and v^c.

    ``noise``: the network's (r_m2, vc_m) on this batch when already computed. A network with ``innovation``
    runs inside the filter, one epoch at a time, on the prior's innovations.
    """
    from .torch_ekf import batch_ekf, rts_smooth

    try:
        if model.innovation:
            def step(k: int, innovation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
                return model(batch.features[:, k], batch.mask[:, k], innovation)

            out = batch_ekf(batch, None, None, n_systems=n_systems, config=ekf_cfg, noise_step=step)
        else:
            r, vc = model(batch.features, batch.mask) if noise is None else noise
            out = batch_ekf(batch, r.to(torch.float64), vc.to(torch.float64), n_systems=n_systems, config=ekf_cfg)
    except torch.linalg.LinAlgError as err:     # a collapsed R: divergence, as a non-finite loss (exit 3)
        raise FloatingPointError(f"the filter's update failed ({one_line(err)}): the network's R collapsed") from None
    return rts_smooth(out) if smooth else out.pos_ecef_m


@torch.no_grad()
def evaluate(model: LfgnssNet, batches: list[WindowBatch], *, n_systems: int, ekf_cfg, smooth: bool = False,
             up_weight: float = 1.0) -> tuple[float, float]:
    """(3D RMSE [m], availability) over the labelled epochs of whole-sequence batches (``up_weight`` 0: 2D RMSE)."""
    was_training = model.training
    model.eval()
    try:
        sq, n_ok, n_lab = 0.0, 0, 0
        for batch in batches:
            pos = run_filter(model, batch, n_systems=n_systems, ekf_cfg=ekf_cfg, smooth=smooth)
            n_lab += int(torch.isfinite(batch.truth_ecef_m).all(dim=-1).sum())
            L, _ = error_norm_m(pos, batch.truth_ecef_m, up_weight=up_weight)
            sq += float((L.double() ** 2).sum())
            n_ok += int(L.numel())
    finally:
        model.train(was_training)
    rmse = math.sqrt(sq / n_ok) if n_ok else float("nan")
    return rmse, (n_ok / n_lab if n_lab else float("nan"))


def _index_batch(full: WindowBatch, index: np.ndarray) -> WindowBatch:
    idx = torch.as_tensor(index, dtype=torch.long, device=full.pr_m.device)
    return WindowBatch(**{f.name: None if getattr(full, f.name) is None else getattr(full, f.name)[idx]
                          for f in dataclasses.fields(full)})


def jitter_features(batch: WindowBatch, std: float, generator: torch.Generator) -> WindowBatch:
    """``batch`` with Gaussian noise of ``std`` (in the normaliser's standard deviations) on its satellites' features.

    A training-time regulariser (``train.feature_noise``): the network cannot key on exact feature values of
    the few streets it trains on. Every feature column gets it (one-hot ``sys_*`` columns too); padded slots stay
    zero; validation never sees the noise.
    """
    if std <= 0:
        return batch
    noise = torch.randn(batch.features.shape, generator=generator, dtype=batch.features.dtype).to(batch.features.device)
    return dataclasses.replace(batch, features=batch.features + std * noise * batch.mask[..., None])


def _rng_state() -> dict:
    return {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}


def _set_rng_state(state: dict) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])


# --------------------------------------------------------------------------- training

@dataclasses.dataclass
class Prepared:
    """Everything data-dependent a run needs (built once; never from the test split)."""

    feature_names: tuple[str, ...]
    normaliser: Normaliser
    windows: list[Window]
    train_batch: WindowBatch
    val_batches: list[WindowBatch]
    n_systems: int
    fingerprints: list[dict]
    source_files: dict[str, dict[str, str]]
    init: Any = None                # the train.init LfgnssModel, or None
    window_scale: np.ndarray | None = None   # (windows,) factor on each window's errors in the loss (loss.balance)
    spans: list[dict] = dataclasses.field(default_factory=list)   # data_span of every train and val sequence


def _split_hint(dataset_id: str, split: str) -> str:
    """``: [splits] axis = "tow", val = [a, b) in FILE.toml ...`` for a registered dataset's empty split, else ''."""
    from lfgnss import datasets

    spec = datasets.registered().get(dataset_id)
    if spec is None:
        return ""
    bounds = datasets.split_bounds_words(spec, split)
    where = f" in {spec.source}" if spec.source else ""
    return (f": [splits] axis = {spec.split_axis!r}, {bounds or 'no such split'}{where}; check them against the drive "
            f"(python -m lfgnss.datasets{' --register ' + str(spec.source) if spec.source else ''})")


def prepare(config: dict, source=None) -> Prepared:
    """Load train/val Sequences, fit the normaliser on train, cut and collate windows.

    ``source(dataset_id, split, config) -> list[Sequence]`` replaces ``load_sequences`` (e.g. the
    cross-validation folds of ``learning.crossval``).
    """
    data = config["data"]
    for key in ("train_split", "val_split"):
        if set(split_parts(data[key])) & set(_FORBIDDEN_SPLITS):
            raise ValueError(f"data.{key} = {data[key]!r}: the test split may not be used for training or selection")
    source = source or load_sequences
    train_seqs, val_seqs, prints, spans, train_ds = [], [], [], [], []
    for ds in data["datasets"]:
        for split, bucket in ((data["train_split"], train_seqs), (data["val_split"], val_seqs)):
            seqs = source(ds, split, config)
            if not seqs:
                raise ValueError(f"dataset {ds!r} split {split!r} gave no sequence{_split_hint(ds, split)}")
            bucket.extend(seqs)
            if bucket is train_seqs:
                train_ds.extend([ds] * len(seqs))
            prints.extend({"dataset": ds, "split": split, "sequence": s.name, "epochs": len(s),
                           "sha256_16": fingerprint(s)} for s in seqs)
            spans.extend(data_span(ds, split, s) for s in seqs)
    names = resolve_feature_names(data["features"], data["drop_features"])
    init = init_model(config)
    if init is not None and tuple(names) != init.feature_names:
        raise ValueError(f"train.init: {init.path} takes features {list(init.feature_names)}, the configuration "
                         f"gives {list(names)} (use adopt_init)")
    # a fine-tuned network keeps the normalisation its weights were trained with
    logged = signed_log_names(data["signed_log"], names, config["model"].get("r_prior"))
    normaliser = Normaliser.fit(train_seqs, names, logged) if init is None else init.normaliser
    n_systems = max(len(s.systems) for s in train_seqs + val_seqs)
    windows = make_windows(train_seqs, int(data["window"]), int(data["stride"]), int(data.get("burn_in", 0)))
    short = [f"{s.name} ({int(s.labelled.sum())} labelled epochs)" for s in train_seqs
             if s.labelled.any() and len(s) < data["window"]]
    if short:
        print(f"note: {len(short)} training piece(s) shorter than the {data['window']}-epoch window are not trained "
              f"on: {', '.join(short)}", file=sys.stderr)
    n_slots = max(s.n_slots for s in train_seqs)
    train_batch = collate(train_seqs, windows, normaliser, n_slots=n_slots, n_systems=n_systems)
    val_batches = [sequence_batch(s, normaliser, n_systems=n_systems) for s in val_seqs]
    files = {ds: source_file_hashes(ds) for ds in data["datasets"]}
    scale = None
    if config["loss"].get("balance", "none") == "plain_ekf":
        per_dataset = dataset_balance(train_seqs, train_ds, ekf_config(config))
        scale = np.array([per_dataset[train_ds[w.seq_index]] for w in windows])
    return Prepared(names, normaliser, windows, train_batch, val_batches, n_systems, prints, files, init, scale, spans)


def dataset_balance(sequences: list[Sequence], dataset_ids: list[str], ekf_cfg) -> dict[str, float]:
    """``loss.balance = "plain_ekf"``: each dataset's factor on its errors, c / s_d [1].

    s_d is the 3D RMSE [m] of the plain EKF (hand-set noise, the training filter) over dataset d's labelled training
    epochs, c their geometric mean: each dataset's errors count relative to how hard it is, so one with large errors
    (a deep urban drive) does not drown the others in a joint loss, while the loss stays near metres.
    """
    import estimators

    plain = estimators.create("plain-ekf", config=ekf_cfg)
    squares: dict[str, list[np.ndarray]] = {}
    for seq, ds in zip(sequences, dataset_ids):
        if not seq.labelled.any():
            continue
        sol = plain.solve(seq)
        err = sol.pos_ecef_m[seq.labelled] - seq.truth_ecef_m[seq.labelled]
        squares.setdefault(ds, []).append(np.sum(err ** 2, axis=1))
    with warnings.catch_warnings():         # an all-NaN dataset is reported below, not as a RuntimeWarning
        warnings.simplefilter("ignore", RuntimeWarning)
        rmse = {ds: float(np.sqrt(np.nanmean(np.concatenate(v)))) for ds, v in squares.items()}
    bad = [ds for ds, v in rmse.items() if not (np.isfinite(v) and v > 0)]
    if bad:
        raise ValueError(f"loss.balance: the plain EKF has no finite, non-zero error on the training epochs of "
                         f"{', '.join(bad)} to scale by ({', '.join(f'{rmse[d]}' for d in bad)} m)")
    log_c = float(np.mean(np.log(list(rmse.values()))))
    factors = {ds: float(np.exp(log_c - np.log(v))) for ds, v in rmse.items()}   # exactly 1 for one dataset
    print("loss.balance: plain EKF 3D RMSE on the training epochs "
          + ", ".join(f"{ds} {v:.2f} m (x{factors[ds]:.2f})" for ds, v in rmse.items()), file=sys.stderr)
    return factors


def _write_log(path: Path, history: list[dict]) -> None:
    """``log.csv``: one row per epoch; epoch 0 (the untrained or ``train.init`` network, validated before any step)
    has no ``train_loss``, so that cell is empty (it used to read ``nan``, which looked like a diverged epoch)."""
    def write(tmp: Path) -> None:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=["epoch", "train_loss", "val_rmse_3d_m", "val_availability", "lr",
                                               "seconds"])
            w.writeheader()
            w.writerows({**h, "train_loss": "" if h["epoch"] == 0 else h["train_loss"]} for h in history)

    replace_atomically(path, write)


def _plot(path: Path, history: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    ep = [h["epoch"] for h in history]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(10, 4))
    a1.plot(ep[1:], [h["train_loss"] for h in history[1:]], "o-")
    a1.set_xlabel("epoch"), a1.set_ylabel("train loss [m]"), a1.set_title("training loss")
    a2.plot(ep, [h["val_rmse_3d_m"] for h in history], "o-", color="C1")
    a2.set_xlabel("epoch"), a2.set_ylabel("3D RMSE [m]"), a2.set_title("validation (whole sequences)")
    for a in (a1, a2):
        a.xaxis.set_major_locator(MaxNLocator(integer=True))      # epochs are whole: no 0.5 ticks on short runs
        a.grid(alpha=0.3)
    fig.tight_layout()
    replace_atomically(path, lambda tmp: fig.savefig(tmp, dpi=100, format="png"))
    plt.close(fig)


def _numpy_globals() -> list:
    """What a checkpoint's numpy arrays (the RNG state) unpickle with, for ``torch.load(weights_only=True)``: under
    both of numpy's module names, so a checkpoint written with numpy 1 reads with numpy 2 and back."""
    core = "numpy._core.multiarray" if int(np.__version__.split(".")[0]) >= 2 else "numpy.core.multiarray"
    reconstruct = importlib.import_module(core)._reconstruct
    dtypes = getattr(np, "dtypes", None)
    return [*((reconstruct, f"{name}._reconstruct") for name in ("numpy._core.multiarray", "numpy.core.multiarray")),
            np.ndarray, np.dtype, *(getattr(dtypes, n) for n in dir(dtypes) if n.endswith("DType"))]


def read_checkpoint(path: str | Path) -> Any:
    """``torch.load`` of a checkpoint file on the CPU, unpickling only tensors, plain containers and numpy arrays
    (``weights_only``: a checkpoint from elsewhere, e.g. a ``--reuse`` folder, cannot run code when read); ValueError
    for a file that holds anything else."""
    with torch.serialization.safe_globals(_numpy_globals()):
        try:
            return torch.load(path, map_location="cpu", weights_only=True)
        except pickle.UnpicklingError as exc:
            operand = re.search(r"Unsupported operand (\d+)", str(exc))
            if operand:     # an instruction torch's safe reader lacks: text, random bytes, or a newer pickle's FRAME
                newer = " or one written with pickle protocol 4 or higher" if operand[1] == "149" else ""
                raise ValueError(f"not a torch file{newer} (UnpicklingError: unknown pickle operand "
                                 f"{operand[1]})") from None
            found = re.search(r"GLOBAL (\S+)|got <class '([^']+)'>", str(exc))
            what = f" ({found[1] or found[2]})" if found else ""
            raise ValueError(f"it holds an object other than tensors, plain containers and numpy arrays{what}, which "
                             f"is not read (it could run code)") from None
        except EOFError:
            raise ValueError("not a torch file (it ends before its first record: empty or cut short)") from None
        except Exception as exc:
            if isinstance(exc, (OSError, RuntimeError, ValueError)):
                raise
            # torch's reader of old-style files fails with IndexError, struct.error, ... on text or other files
            raise ValueError(f"not a torch file ({type(exc).__name__}: {exc})") from None


def load_checkpoint(path: str | Path) -> dict:
    """A ``last.pt`` of ``learning.train``, or ValueError naming it in one line (a truncated or foreign file)."""
    try:
        saved = read_checkpoint(path)
        if not isinstance(saved, dict) or not isinstance(saved.get("config"), dict):
            raise ValueError("no training configuration in it")
        int(saved["epoch"])
    except Exception as exc:            # torch.load raises many kinds on a file that is not a whole checkpoint
        raise _unreadable(path, exc) from None
    return saved


def _unreadable(path: str | Path, exc: BaseException) -> ValueError:
    """The one-line error of a checkpoint that cannot be resumed from."""
    return ValueError(f"{path}: cannot read the checkpoint ({type(exc).__name__}: "
                      f"{shortened(one_line(exc), 200)}); start a new --out")


def resumed_config(saved: dict, overrides: list[str], where: str | Path) -> dict:
    """The configuration a resumed run goes on with: the checkpoint ``saved``'s, with only the RESUME_FREE settings
    of ``overrides``; ValueError naming a setting they would change otherwise (with both values), or a
    ``train.epochs`` below the epoch the checkpoint holds."""
    before = _merge_free(DEFAULT_CONFIG, saved["config"])        # a run from before a key: its default
    given = check_config(apply_overrides(before, list(overrides)))
    was, now = _flat(before), _flat(given)
    for config, flat in ((before, was), (given, now)):            # the filter as it runs: an unset key is its default
        flat.update({f"ekf.{k}": v for k, v in dataclasses.asdict(ekf_config(config)).items()})
    given_keys = [item.split("=", 1)[0].strip() for item in overrides]          # named in the order given
    changed = sorted((k for k in was.keys() | now.keys()
                      if k not in RESUME_FREE and was.get(k, "(unset)") != now.get(k, "(unset)")),
                     key=lambda k: (given_keys.index(k) if k in given_keys else len(given_keys), k))
    if changed:
        k = changed[0]
        also = f"; nor can {', '.join(changed[1:])}" if len(changed) > 1 else ""
        raise ValueError(f"{where}: {k} cannot change on --resume ({was.get(k, '(unset)')!r} -> "
                         f"{now.get(k, '(unset)')!r}{also}); {_RESUME_RULE} (start a new --out to train otherwise)")
    epoch, epochs = int(saved["epoch"]), int(given["train"]["epochs"])
    if epochs < epoch:
        raise ValueError(f"{where}: holds epoch {epoch} already, train.epochs = {epochs} is fewer; --resume can only "
                         f"extend the schedule (train.epochs >= {epoch})")
    config = copy.deepcopy(saved["config"])
    for key in RESUME_FREE:
        if _setting(given, key) != _setting(config, key):
            *parents, leaf = key.split(".")
            table = config
            for part in parents:
                table = table.setdefault(part, {})
            table[leaf] = _setting(given, key)
    return config


def _warn_ignored_config(config: dict | None, checkpoint: dict, overrides: list[str], where: Path) -> None:
    """A warning when ``train(config, resume=True)`` is given a configuration other than the checkpoint's: a resumed
    run goes on with its own, so the differences would go unseen (the command line passes none)."""
    if config is None:
        return
    given = {k.split("=", 1)[0].strip() for k in overrides}
    was = _flat(_merge_free(DEFAULT_CONFIG, checkpoint["config"]))
    try:                                            # files as the run recorded them (absolute), where they exist
        now = _flat(_files_absolute(config))
    except (KeyError, TypeError):                   # a configuration without those tables: compared as given
        now = _flat(config)
    differ = sorted(k for k in was.keys() & now.keys() if was[k] != now[k] and k not in given
                    and not k.startswith(("model.", "data.features", "data.drop_features", "data.signed_log")))
    # (those are train.init's own)
    if differ:
        k = differ[0]
        warnings.warn(f"{where}: resuming goes on with the checkpoint's configuration, not the one given ({k} "
                      f"{was[k]!r} there, {now[k]!r} given{f'; {len(differ) - 1} more' if len(differ) > 1 else ''}); "
                      "only train.epochs, threads and device may change, as overrides "
                      "(overrides=['train.epochs=N'])", stacklevel=3)


def _config_file_record(config_file: str | Path) -> dict:
    """What a checkpoint keeps of the ``--config`` file its run was started from: the path, and the settings read."""
    return {"path": str(Path(config_file).resolve()), "settings": _read_toml(Path(config_file))}


def _check_config_file(config_file: str | Path, record: dict | None, where: Path) -> None:
    """ValueError unless ``config_file`` (``--config`` given with ``--resume``) is the file, unchanged, that the run
    of the checkpoint ``where`` was started from (its ``record``): a resumed run reads nothing new from it."""
    leave_out = f"{_RESUME_RULE}; leave out --config (--resume --out {where.parent})"
    started = (record or {}).get("path")
    if str(Path(config_file).resolve()) != started:
        origin = f"from {started}" if started else "without a --config it recorded"
        raise ValueError(f"--config {config_file}: {where} was started {origin}; {leave_out}")
    was, now = _flat(record.get("settings") or {}), _flat(_read_toml(Path(config_file)))
    changed = sorted(k for k in was.keys() | now.keys() if was.get(k, "(unset)") != now.get(k, "(unset)"))
    if changed:
        k = changed[0]
        raise ValueError(f"{config_file}: {k} is {now.get(k, '(unset)')!r} now, {was.get(k, '(unset)')!r} when {where} "
                         f"was started; {leave_out}")


_UNSET = object()


def _shown(value: object) -> str:
    """A setting's value in a message: its repr, or ``unset``."""
    return "unset" if value is _UNSET else repr(value)


def _check_dataset_tomls(checkpoint: dict, where: Path) -> None:
    """ValueError naming a dataset TOML (``data.register``) of the run of the checkpoint ``where`` that is missing or
    reads otherwise than when the run was started (its text is in the run's ``provenance``): a resumed run goes on
    with the data it was started with, or its log.csv would mix two validation splits and best.pt compare them."""
    recorded = (checkpoint.get("provenance") or {}).get("dataset_tomls") or {}
    model = where.parent / "model.npz"
    kept = (f"its text is recorded in the run: python -m learning.export --show {model} names it"
            if model.is_file() else f"its text is recorded in {where}")
    for path, was in recorded.items():
        if not isinstance(was, str) or was.startswith("(not readable:"):   # not read when the run started
            continue
        try:
            now = Path(path).read_text()
        except FileNotFoundError:
            raise ValueError(f"{path}: the run in {where.parent} was registered from this dataset TOML, which is "
                             f"missing now; put it back as it was to --resume ({kept}), or start a new --out") from None
        except (OSError, UnicodeDecodeError):
            continue                                    # register_toml says what is wrong with it, as for a new run
        change = dataset_toml_change(was, now)
        if change is not None:
            raise ValueError(f"{path}: {change} when {where} was started; a resumed run goes on with the data it was "
                             "started with (log.csv and the best epoch would compare two splits): put the file back "
                             f"as it was ({kept}), or start a new --out")


def _check_source_files(checkpoint: dict, now: dict[str, dict[str, str]], where: Path) -> None:
    """ValueError naming an input file of the run of the checkpoint ``where`` whose content is not what it was when the
    run started (``source_files``: dataset -> file name -> SHA-256, 16 hex digits; runs of before session 49 hashed a
    gzip file's bytes, which count too): a resumed run goes on with the data it was started with."""
    for dataset_id, recorded in (checkpoint.get("source_files") or {}).items():
        current = now.get(dataset_id) or {}
        changed = [name for name, digest in (recorded or {}).items() if name in current and current[name] != digest]
        if not changed:
            continue
        paths = {Path(p).name: p for p in get(dataset_id).files()}
        as_bytes = file_hashes([paths[n] for n in changed if n in paths], content=False)
        changed = [n for n in changed if as_bytes.get(n) != recorded[n]]
        if changed:
            raise ValueError(f"{paths.get(changed[0], changed[0])}: its content differs from when {where} was "
                             f"started (dataset {dataset_id}); a resumed run goes on with the data it was started with "
                             "(log.csv and the best epoch would compare two data sets): put the file back as it was, "
                             "or start a new --out")


def _data_settings(flat: dict) -> dict:
    """A flattened dataset TOML without the keys that change no data: ``description``, a ``time_offset_s`` of 0 and a
    ``time_origin_gps_s`` that neither a smartloc truth nor relative_s splits read (refused at registration since
    session 50, so a run started before then resumes once it is removed)."""
    fmt = str(flat.get("truth.format", "urbannav")).lower()
    axis = str(flat.get("splits.axis", "tow")).lower()
    unread = {"description"} | ({"truth.time_origin_gps_s"} if fmt != "smartloc" and axis != "relative_s" else set())
    unread |= {"truth.time_offset_s"} if flat.get("truth.time_offset_s") == 0 else set()     # the default
    return {k: v for k, v in flat.items() if k not in unread}


def dataset_toml_change(was: str, now: str) -> str | None:
    """The first key in which two texts of a dataset TOML differ in what they make of the data, ``splits.val is [0, 9]
    now, [0, 8]``; that the text differs where either does not parse; None where they hold the same data settings
    (comments, layout and ``_data_settings``' keys aside)."""
    if was == now:
        return None
    try:
        before, after = (_data_settings(_flat(tomllib.loads(text))) for text in (was, now))
    except tomllib.TOMLDecodeError:
        return "its text differs from the text it had"
    changed = sorted(k for k in before.keys() | after.keys() if before.get(k, _UNSET) != after.get(k, _UNSET))
    if not changed:
        return None
    k = changed[0]
    return f"{k} is {_shown(after.get(k, _UNSET))} now, {_shown(before.get(k, _UNSET))}"


def train(config: dict | None, out_dir: str | Path, *, resume: bool = False, overrides: list[str] = (),
          progress: bool = True, prepared: Prepared | None = None, export: bool = True,
          config_file: str | Path | None = None, command: str | None = None,
          epoch_lines: bool | None = None) -> list[dict]:
    """Run (or resume) training; returns the history rows (epoch 0 = untrained model).

    Parameters
    ----------
    config : dict, or None with ``resume``
        Full configuration (``load_config``). A resumed run goes on with its checkpoint's; one given that differs
        from it is warned of.
    out_dir : path
        Run folder for ``last.pt``, ``best.pt``, ``log.csv``, ``curves.png``, ``model.npz``.
    resume : bool
        Continue from ``out_dir/last.pt`` exactly (same shuffles, optimiser and scheduler state). The
        checkpoint's configuration is the run's (a ``config`` that differs is warned of): ``overrides`` may change only
        ``RESUME_FREE`` settings (e.g. ``["train.epochs=300"]``, to extend the schedule); any other that differs from
        the checkpoint's is refused (``resumed_config``).
    prepared : Prepared, optional
        Pre-built data (tests reuse it across runs); built from ``config`` otherwise.
    config_file : path, optional
        The ``--config`` file ``config`` was read from: recorded in the checkpoints; with ``resume``, refused unless
        it is that run's own file, unchanged.
    command : str, optional
        The command line that started (or resumed) the run: recorded with the git commit and the dataset TOMLs
        (``learning.provenance``) in the checkpoints and the model file.
    progress : bool
        A progress bar per epoch on stderr, drawn only where stderr is a terminal.
    epoch_lines : bool, optional
        Print a result line per epoch on stdout (epoch 0 included), and say so when a resumed run is already at
        ``train.epochs``; default: as ``progress`` (the command lines print them, ``--no-progress`` or not).
    """
    epoch_lines = progress if epoch_lines is None else epoch_lines
    out = Path(out_dir)                       # made only once the settings and the data are found good (_train)
    last_path = out / "last.pt"
    checkpoint = None
    if resume:
        if not last_path.exists():
            raise ValueError(f"{last_path}: no checkpoint to resume from")
        checkpoint = load_checkpoint(last_path)
        record = checkpoint.get("config_file")
        if config_file is not None:
            _check_config_file(config_file, record, last_path)
        _warn_ignored_config(config, checkpoint, list(overrides), last_path)
        config = resumed_config(checkpoint, list(overrides), last_path)
        _check_dataset_tomls(checkpoint, last_path)
        done, epochs = int(checkpoint["epoch"]), int(config["train"]["epochs"])
        t_max, planned = int(config["train"]["t_max"]), int(checkpoint["config"]["train"]["epochs"])
        if planned <= t_max < epochs:           # a schedule made to end annealed, taken past its turn
            warnings.warn(f"{last_path}: train.epochs = {epochs} goes past train.t_max = {t_max}, where the cosine "
                          "schedule turns: the learning rate climbs back towards train.lr (the run was planned for "
                          f"{planned} epochs, annealed at the end)", stacklevel=2)
        if done >= epochs and epoch_lines:      # nothing to train (model.npz is written again, as it was)
            print(f"{out}: already at epoch {done} of {epochs}; extend with --set train.epochs=M (M > {done})",
                  flush=True)
    elif config is None:
        raise ValueError("train: config is None; give a configuration (learning.train.load_config) for a new run")
    elif last_path.exists():
        raise ValueError(f"{last_path}: a run already exists here; pass --resume or choose another --out")
    else:
        record = None if config_file is None else _config_file_record(config_file)
    check_config(config)
    if checkpoint is None:
        config = adopt_init(_files_absolute(config))     # a resumed run's checkpoint config has both already
    made = provenance.run_record(command, config)
    if checkpoint is not None:          # the run's own record, with this resumption added
        started = checkpoint.get("provenance") or {}
        made = {**started, "resumes": [*started.get("resumes", []), made]}
    data = config["data"]
    if set(split_parts(data["val_split"])) & set(split_parts(data["train_split"])):
        seen = f"data.val_split {data['val_split']!r} is trained on (data.train_split {data['train_split']!r})"
        print(f"warning: {seen}: the run's epoch is chosen on its own training data, so best.pt and its validation "
              "RMSE are optimistic; use a held-out split, or train.select = \"last\" with a schedule chosen by "
              "learning.crossval" if config["train"]["select"] == "val" else
              f"note: {seen}: its validation RMSE is optimistic; train.select = \"last\" chooses nothing on it",
              file=sys.stderr)

    deterministic = torch.are_deterministic_algorithms_enabled()
    on_gpu = resolve_device(config.get("device", "cpu")).type == "cuda"
    if on_gpu:
        # cuBLAS is deterministic only with a fixed workspace; must be set before its first use in the process
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
        print("note: on CUDA a run repeats to rounding, not bit for bit (torch has no deterministic CUDA nanmedian "
              "or attention backward); it matches the CPU to about 1e-5 m", file=sys.stderr)
    torch.use_deterministic_algorithms(True, warn_only=True)
    last_saved = {"epoch": None if checkpoint is None else int(checkpoint["epoch"])}   # the epoch last.pt holds
    try:
        with warnings.catch_warnings(), torch_threads(int(config["threads"])):
            if on_gpu:                                  # said once above instead of at every kernel
                warnings.filterwarnings("ignore", ".*does not have a deterministic implementation", UserWarning)
                warnings.filterwarnings("ignore", ".*defaults to a non-deterministic algorithm", UserWarning)
            return _train(config, out, checkpoint, progress=progress, epoch_lines=epoch_lines, prepared=prepared,
                          export=export,
                          config_record=record, last_saved=last_saved, made=made)
    except KeyboardInterrupt as exc:                    # main says what is kept and how to go on
        exc.last_saved_epoch = last_saved["epoch"]
        raise
    finally:
        torch.use_deterministic_algorithms(deterministic)


def _train(config: dict, out: Path, checkpoint: dict | None, *, progress: bool, epoch_lines: bool,
           prepared: Prepared | None,
           export: bool, config_record: dict | None = None, last_saved: dict | None = None,
           made: dict | None = None) -> list[dict]:
    last_path, best_path = out / "last.pt", out / "best.pt"
    seed = int(config["seed"])
    torch.manual_seed(seed)
    np.random.seed(seed)
    random.seed(seed)

    prep = prepared or prepare(config)
    if checkpoint is not None:
        _check_source_files(checkpoint, prep.source_files, last_path)
    elif prepared is None and prep.init is not None:       # learning.crossval says so of its blocks itself
        for line in init_saw_validation(prep.init, config):
            print(f"warning: train.init {prep.init.path} {line}: the validation split is not unseen data, so its "
                  "RMSE, the starting model's at epoch 0 included, is optimistic", file=sys.stderr)
    device = resolve_device(config.get("device", "cpu"))      # runs from before the setting resume on the CPU
    train_batch, val_batches = prep.train_batch.to(device), [b.to(device) for b in prep.val_batches]
    ekf_cfg = ekf_config(config)
    tr = config["train"]
    smooth = bool(tr.get("smooth", False))   # train and validate the RTS-smoothed positions (estimators.smoother)
    model = build_model(config, len(prep.feature_names), prep.normaliser)
    if prep.init is not None:
        if model.hyperparameters() != model_settings(prep.init.metadata):
            raise ValueError(f"train.init: {prep.init.path} cannot be rebuilt from its training configuration "
                             f"({prep.init.metadata['model']} vs {model.hyperparameters()})")
        model.load_state_dict({k: torch.as_tensor(v) for k, v in prep.init.params.items()})
    model.to(device)                          # initialised on the CPU, so a seed gives the same start on any device
    started_from = None if prep.init is None else init_record(prep.init)
    out.mkdir(parents=True, exist_ok=True)
    decay = float(tr.get("weight_decay", 0.0))
    # Adam as in the paper; decoupled weight decay (AdamW) only when asked for, so 0 is the paper's optimiser.
    frozen = tuple(tr.get("freeze", ()))       # runs from before the setting resume with nothing frozen
    for name, param in model.named_parameters():
        param.requires_grad_(name.split(".")[0] not in frozen)
    trained = [p for p in model.parameters() if p.requires_grad]
    optimiser = (torch.optim.AdamW(trained, lr=float(tr["lr"]), weight_decay=decay) if decay > 0
                 else torch.optim.Adam(trained, lr=float(tr["lr"])))
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, T_max=int(tr["t_max"]),
                                                           eta_min=float(tr["eta_min"]))
    ema_decay = float(tr.get("ema_decay", 0.0))
    averaged = (torch.optim.swa_utils.AveragedModel(
        model, multi_avg_fn=torch.optim.swa_utils.get_ema_multi_avg_fn(ema_decay)) if ema_decay > 0 else None)
    weights = model if averaged is None else averaged.module    # the weights validated, saved and exported
    lc = config["loss"]
    loss_fn = make_loss(lc["kind"], alpha=float(lc["alpha"]), gamma=float(lc["gamma"]), lam=float(lc["lambda"]),
                        up_weight=float(lc.get("up_weight", 1.0)))   # runs from before it resume
    vc_weight, vc_delta = float(lc.get("vc_weight", 0.0)), float(lc.get("vc_delta_m", 5.0))
    r_weight, strongest_clock = float(lc.get("r_weight", 0.0)), lc.get("r_clock", "median") == "strongest"
    history: list[dict] = []
    best = float("inf")
    start_epoch = 1

    def save(path: Path, epoch: int) -> None:
        extra = {} if averaged is None else {"trained_model": model.state_dict(),
                                             "ema_n_averaged": int(averaged.n_averaged)}
        state = {"model": weights.state_dict(), **extra, "model_hparams": model.hyperparameters(),
                 "optimiser": optimiser.state_dict(), "scheduler": scheduler.state_dict(), "epoch": epoch,
                 "history": history, "best_val_rmse_3d_m": best, "rng": _rng_state(),
                 "normaliser": prep.normaliser.to_dict(), "feature_names": list(prep.feature_names),
                 "n_systems": prep.n_systems, "config": config, "ekf_config": dataclasses.asdict(ekf_cfg),
                 "data_fingerprints": prep.fingerprints, "data_spans": prep.spans, "source_files": prep.source_files,
                 "init_model": started_from, "config_file": config_record, "provenance": made}
        replace_atomically(path, lambda tmp: torch.save(state, tmp))
        if path == last_path and last_saved is not None:
            last_saved["epoch"] = epoch

    if checkpoint is not None:
        try:
            model.load_state_dict(checkpoint["model" if averaged is None else "trained_model"])
            if averaged is not None:
                averaged.module.load_state_dict(checkpoint["model"])
                averaged.n_averaged.fill_(int(checkpoint["ema_n_averaged"]))
            optimiser.load_state_dict(checkpoint["optimiser"])
            scheduler.load_state_dict(checkpoint["scheduler"])
            history = list(checkpoint["history"])
            best = float(checkpoint["best_val_rmse_3d_m"])
            start_epoch = int(checkpoint["epoch"]) + 1
            _set_rng_state(checkpoint["rng"])
        except Exception as exc:            # a checkpoint that reads but does not fit this network or optimiser
            raise _unreadable(last_path, exc) from None
    else:
        t0 = time.perf_counter()
        val, avail = evaluate(weights, val_batches, n_systems=prep.n_systems, ekf_cfg=ekf_cfg, smooth=smooth)
        history.append({"epoch": 0, "train_loss": float("nan"), "val_rmse_3d_m": val, "val_availability": avail,
                        "lr": optimiser.param_groups[0]["lr"], "seconds": time.perf_counter() - t0})
        best = val
        save(best_path, 0)
        save(last_path, 0)
        start = "start: train.init model" if prep.init is not None else "untrained"   # what training has to beat
        if epoch_lines:
            print(f"epoch 0 ({start}): val 3D RMSE {val:.3f} m ({history[-1]['seconds']:.1f} s)", flush=True)

    n_windows = len(prep.windows)
    batch_size = int(tr["batch_size"])
    feature_noise = float(tr.get("feature_noise", 0.0))
    for epoch in range(start_epoch, int(tr["epochs"]) + 1):
        t0 = time.perf_counter()
        model.train()
        order = np.random.default_rng([seed, epoch]).permutation(n_windows)
        chunks = [order[k:k + batch_size] for k in range(0, n_windows, batch_size)]
        lr = optimiser.param_groups[0]["lr"]
        total, count = 0.0, 0
        if progress:        # disable=None: a bar only where stderr is a terminal, as estimators.base.epoch_range
            from tqdm.auto import tqdm

            chunks = tqdm(chunks, desc=f"epoch {epoch}/{tr['epochs']}", unit="batch", disable=None, leave=False,
                          file=sys.stderr)
        jitter = torch.Generator().manual_seed(int(seed) * 100_003 + epoch)
        for idx in chunks:
            batch = jitter_features(_index_batch(train_batch, idx), feature_noise, jitter)
            noise = model(batch.features, batch.mask) if vc_weight > 0 or r_weight > 0 else None
            pos = run_filter(model, batch, n_systems=prep.n_systems, ekf_cfg=ekf_cfg, smooth=smooth, noise=noise)
            k = 1.0                                 # errors scaled per dataset (loss.balance)
            if prep.window_scale is not None:
                k = torch.as_tensor(prep.window_scale[idx], dtype=pos.dtype, device=pos.device)[:, None, None]
                truth = batch.truth_ecef_m
                pos = truth + k * (pos - truth)
            loss = loss_fn(pos, batch.truth_ecef_m)
            if noise is not None:                   # supervised per satellite by the true error (loss.vc_weight,
                usable, error = labelled_errors_m(batch, prep.n_systems)                       # loss.r_weight)
                if vc_weight > 0:
                    loss = loss + vc_weight * compensation_loss(k * noise[1], k * error, usable, batch.system_index,
                                                                prep.n_systems, delta_m=vc_delta)
                if r_weight > 0:                    # scale free: loss.balance's k would shift it by a constant
                    loss = loss + r_weight * variance_loss(noise[0], noise[1], error, usable, batch.system_index,
                                                           prep.n_systems,
                                                           batch.cn0_dbhz if strongest_clock else None)
            if not torch.isfinite(loss):
                raise FloatingPointError(f"epoch {epoch}: non-finite training loss {float(loss.detach())}")
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            # a finite loss can still have NaN gradients, and one Adam step with them makes every weight NaN
            grads = [p.grad for p in model.parameters() if p.grad is not None]
            if grads and not bool(torch.stack([torch.isfinite(g).all() for g in grads]).all()):   # one device sync
                raise FloatingPointError(f"epoch {epoch}: non-finite gradient of a finite training loss "
                                         f"{float(loss.detach()):g}")
            if float(tr["grad_clip"]) > 0:
                torch.nn.utils.clip_grad_norm_(model.parameters(), float(tr["grad_clip"]))
            optimiser.step()
            total += float(loss.detach()) * len(idx)
            count += len(idx)
            if progress:
                chunks.set_postfix(loss=f"{float(loss.detach()):.3f}", refresh=False)
        scheduler.step()
        if averaged is not None:
            averaged.update_parameters(model)
        val, avail = evaluate(weights, val_batches, n_systems=prep.n_systems, ekf_cfg=ekf_cfg, smooth=smooth)
        history.append({"epoch": epoch, "train_loss": total / count, "val_rmse_3d_m": val, "val_availability": avail,
                        "lr": lr, "seconds": time.perf_counter() - t0})
        if val < best:
            best = val
            save(best_path, epoch)
        save(last_path, epoch)
        _write_log(out / "log.csv", history)
        if epoch_lines:
            print(f"epoch {epoch}: train loss {total / count:.3f} m, val 3D RMSE {val:.3f} m "
                  f"({history[-1]['seconds']:.1f} s)", flush=True)
    _write_log(out / "log.csv", history)
    _plot(out / "curves.png", history)
    if export:
        from .export import export_model

        chosen = last_path if tr.get("select", "val") == "last" else best_path
        export_model(chosen, out / "model.npz")               # written atomically
    return history


def exit_on_input_error(parser: argparse.ArgumentParser, exc: BaseException) -> None:
    """Exit 2 with ``PROG: error: MESSAGE`` on one line, for bad input (``lfgnss.errors.INPUT_ERRORS``)."""
    parser.exit(2, f"{parser.prog}: error: {one_line(exc)}\n")


def _resume_hint(exc: BaseException, out: Path) -> str:
    """What an interrupted run keeps, for its one line: the epoch ``last.pt`` holds and the command that goes on."""
    last, epoch = out / "last.pt", getattr(exc, "last_saved_epoch", None)
    go_on = f"continue with --resume --out {shlex.quote(str(out))}"
    if epoch is not None:
        return f"; {last} holds epoch {epoch}: {go_on}"
    if last.is_file():                        # stopped while reading it: as it was
        return f"; {last} is as it was: {go_on}"
    return " before the first checkpoint was written (nothing to resume)"


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point.

    Exit status 0; 2 for bad input (one line ``PROG: error: ...``); 3 for a non-finite training loss or gradient;
    130 for Ctrl-C (one line naming the epoch ``last.pt`` holds, and how to resume).
    """
    p = argparse.ArgumentParser(prog="python -m learning.train", description=__doc__.split("\n")[0],
                                formatter_class=PlainHelp)
    p.add_argument("--config", type=config_path, help="TOML configuration: a file, or the name of a shipped one ("
                   f"{', '.join(shipped_configs())}; default: built-in defaults)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a configuration key, e.g. --set train.epochs=5, --set threads=4 (CPU threads), "
                        "--set device=cuda (cpu, cuda, cuda:N or auto) (repeatable)")
    p.add_argument("--out", type=path_option, help="run folder (default: runs/<config name>)")
    p.add_argument("--resume", action="store_true",
                   help="continue from OUT/last.pt with the run's own configuration (only --set train.epochs=N, "
                        "threads and device may change)")
    p.add_argument("--no-progress", action="store_true",
                   help="no progress bars (the per-epoch result lines are printed all the same; the bars are drawn "
                        "only where stderr is a terminal)")
    args = p.parse_args(argv)
    out = str(args.out or Path("runs") / (Path(args.config).stem if args.config else "default"))
    try:
        with warnings_on_one_line():
            config = load_config(args.config, args.overrides)
            check_output_folder(out)            # before the data are built: a file or a read-only disk costs nothing
            history = train(None if args.resume else config, out, resume=args.resume, overrides=args.overrides,
                            progress=not args.no_progress,
                            epoch_lines=True, config_file=args.config,
                            command=provenance.command_line(p.prog, sys.argv[1:] if argv is None else list(argv)))
    except INPUT_ERRORS as exc:
        exit_on_input_error(p, exc)
    except KeyboardInterrupt as exc:          # Ctrl-C: one line saying what is kept and how to go on
        p.exit(130, f"{p.prog}: interrupted{_resume_hint(exc, Path(out))}\n")
    except FloatingPointError as exc:         # diverged: not bad input (exit 3, not 2); the checkpoints stay
        p.exit(3, f"{p.prog}: error: {one_line(exc)}: training stopped (exit status 3); the checkpoints of the "
                  f"epochs before it are kept in {out} (last.pt, best.pt); check [loss], or try a lower train.lr or "
                  "a train.grad_clip > 0, in a new --out\n")
    from .export import load_model, trained_smoothed

    best = min(history, key=lambda h: h["val_rmse_3d_m"])
    exported = load_model(Path(out) / "model.npz").metadata     # the run's own config decides (--resume)
    model = shlex.quote(str(Path(out) / "model.npz"))
    print(f"{out}: best validation 3D RMSE {best['val_rmse_3d_m']:.3f} m at epoch {best['epoch']}; model "
          f"{Path(out) / 'model.npz'} is epoch {exported['epoch']} (validation {exported['val_rmse_3d_m']:.3f} m)")
    smooth = " --smooth" if trained_smoothed(exported) else ""
    print(f"use it: python -m lfgnss.solve --model {model}{smooth} --obs OBS --nav NAV ... (without --obs: the bundled "
          f"Berlin drive; python -m learning.export --show {model} describes the model)")
    if exported["epoch"] == 0:
        print(f"warning: no training epoch beat the untrained network on validation, so {Path(out) / 'model.npz'} "
              "holds no training (a network that starts from train.init is that model); train longer, change the "
              "recipe, or set train.select = \"last\"", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
