"""The LF-GNSS model file: one ``.npz`` that numpy alone can run (no torch at inference).

Format (``FORMAT_NAME`` version ``FORMAT_VERSION``), arrays in one uncompressed ``.npz``:

    metadata            0-d unicode array: JSON with format, format_version, feature_names,
                        model (hyper-parameters), layer_norm_eps, parameters (names, shapes),
                        normaliser, training config, ekf_config, n_systems, data_fingerprints
                        (per sequence: dataset, split, name, epochs, content sha256), data_spans (per
                        sequence: dataset, split, name, first and last GPS time, median truth), source_files
                        (dataset -> file name -> sha256 of the input files), init_model (the
                        model file fine-tuning started from: path, sha256, datasets, train.select, its data
                        fingerprints, spans and source files and its own init_model; null when trained
                        from scratch),
                        config_file (the --config file's path and settings), provenance (the command
                        line, working folder, git commit, dataset TOML texts; ``learning.provenance``),
                        epoch, val_rmse_3d_m, versions (lfgnss, torch, numpy) and created_utc of the export, and
                        refilter (only if the file's filter was changed after training, ``refilter_model``:
                        per change, the settings before and after, command line, git state, time)
    normaliser_mean     (d,) float64   per-feature mean of the training split (valid slots), of sign(x) ln(1 + |x|)
                                       for the features the metadata's normaliser.signed_log names (absent: none)
    normaliser_std      (d,) float64   per-feature std (of the same)
    param/<name>        float32        every tensor of ``LfgnssNet.state_dict()``

Version ``ENSEMBLE_FORMAT_VERSION`` (2) is an ensemble (``export_ensemble``): networks of one recipe trained with
different seeds, run as one noise model (R: geometric mean of the members', v^c: their mean). Its ``param/<name>``
are the first member's, ``member<i>/param/<name>`` the others' (i = 1, 2, ...), and its metadata (the first
member's) adds ``ensemble``: ``combine`` and ``members``, per member its checkpoint, seed, epoch, val_rmse_3d_m,
provenance and, for a network taken from a model file, the first file it came through (``model_file``,
``model_file_sha256_16``) and, trained on another machine's features, its own ``data_fingerprints``; an ensemble grown
from model files lists them in ``ensemble.grown_from`` (path, SHA-256, and how each was put together). Version 1
readers refuse it rather than run one member as if it were the whole.

``load_model`` checks the file and returns an ``LfgnssModel`` whose ``predict`` re-implements the
network's forward pass in numpy (float64), and whose ``__call__(sequence)`` makes it an
``estimators.noise.NoiseModel``. A model trained with ``model.innovation`` reads the filter's prior
innovations too (``online``): the EKF plug-in calls ``predict`` epoch by epoch with them, and
``__call__`` runs that EKF and returns the noise it used (so the factor graph can take it).
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import errno
import json
import shlex
import sys
import zipfile
from pathlib import Path
from typing import Iterable

import numpy as np

from lfgnss.errors import InputError, closest_name, print_stdout, shortened
from lfgnss.features import AVAILABLE_FEATURES
from lfgnss.help_text import PlainHelp
from lfgnss.paths import (MODEL_PREFIX, bundled_models, file_hash, file_hashes, may_name_a_bundled_model,
                          model_path, replace_atomically)
from lfgnss.sequence import Sequence
from lfgnss.weighted_fix import cn0_elevation_variance_m2

from .normalise import Normaliser, select_features

FORMAT_NAME = "lfgnss-noise-model"
FORMAT_VERSION = 1
#: The format version of an ensemble file (``export_ensemble``); a single network is still written as version 1.
ENSEMBLE_FORMAT_VERSION = 2
#: How an ensemble file's members are combined (``learning.network.combine_members``), as its metadata says.
ENSEMBLE_COMBINE = "R: geometric mean of the members'; v^c: mean of the members'"
#: Training settings an ensemble's members may differ in (everything else must be the same recipe and data).
ENSEMBLE_FREE = ("seed", "threads", "device")
#: Variance of padded slots (same as ``learning.network.PAD_R_M2``, repeated to stay torch-free).
PAD_R_M2 = 1.0
#: Epochs per pass of the network in ``LfgnssModel.predict`` (memory is linear in it, the result independent of it).
PREDICT_CHUNK_EPOCHS = 512


class ModelFileError(InputError, ValueError):
    """A model file that cannot be used: ``PATH: reason`` on one line."""


# --------------------------------------------------------------------------- writing

def export_model(checkpoint_path: str | Path, out_path: str | Path, *, extra_metadata: dict | None = None) -> Path:
    """Write the model of a training checkpoint (``learning.train``) as one ``.npz`` model file.

    Parameters
    ----------
    checkpoint_path : path of ``best.pt`` / ``last.pt``
    out_path : destination (``.npz`` is appended by numpy when missing, so give it)
    extra_metadata : merged into the JSON metadata (e.g. source file hashes)

    Returns
    -------
    Path of the written file.
    """
    params, normaliser, meta = _checkpoint_contents(checkpoint_path)
    meta.update(extra_metadata or {})
    return _write_model_file(out_path, params, normaliser, meta)


def export_ensemble(sources: list[str | Path], out_path: str | Path, command: str | None = None) -> Path:
    """Write networks of one recipe, trained with different seeds (checkpoints or model files), as one ensemble file.

    A source may be a model file (``.npz`` or a bundled model's name, single network or ensemble): its networks join
    the ensemble with their records, and the file, its SHA-256 and how it was put together are kept in
    ``ensemble.grown_from``, so seeds trained later grow a shipped ensemble without its members' checkpoints;
    ``out_path`` may be that file (it is replaced only by a file that reads back).
    The networks must share features, normaliser, network, filter and training data; their training
    configurations may differ only in ``ENSEMBLE_FREE`` (and ``train.select`` between ``last.pt`` checkpoints, which
    it does not choose), their seeds must differ (ModelFileError naming the source, the setting and both values; the
    recipe is checked before the seed). ``command``, the working folder and the git state are recorded as how the
    file was put together (``ensemble.exported``). A single checkpoint is written as ``export_model`` writes it.
    """
    paths = [source_file(p) for p in sources]
    if not paths:
        raise ValueError("export_ensemble: no source given")
    if len(paths) == 1 and not str(paths[0]).endswith(".npz"):
        return _write_model_file(out_path, *_checkpoint_contents(paths[0]))
    seen, seeds, networks, records, meta, grown_from = {}, {}, [], [], None, []
    for path in paths:
        if path.resolve() in seen:
            raise ModelFileError(path, f"given twice (as {seen[path.resolve()]}): an ensemble's members are "
                                       "different training runs")
        seen[path.resolve()] = path
        source_networks, grown = _source_networks(path)
        grown_from += [grown] if grown else []
        for net, norm, other, record in source_networks:
            if meta is None:
                params, normaliser, meta, first = net, norm, other, record
            # the recipe first: two runs of other recipes share a seed more often than not (seed 0)
            free = ("train.select",) if _is_last_pt(first) and _is_last_pt(record) else ()
            difference = _member_difference(meta, normaliser, other, norm, free)
            if difference is not None:
                raise ModelFileError(path, f"{difference[0]} differs from {paths[0]}'s ({difference[1]}): an "
                                           "ensemble's members must be one recipe on the same data, differing only "
                                           f"in {', '.join(ENSEMBLE_FREE)}")
            seed = record.get("seed")
            if not isinstance(seed, int) or isinstance(seed, bool) or seed in seeds:
                why = f"has the seed of {seeds[seed]}" if seed in seeds else "records no seed"
                raise ModelFileError(path, f"{why}: an ensemble's members are runs of one recipe with different "
                                           "seeds (learning.train --set seed=S)")
            seeds[seed] = path
            if not meta.get("data_spans") and other.get("data_spans"):   # the same data; older files lack spans
                meta = {**meta, "data_spans": other["data_spans"]}
            if other.get("data_fingerprints") != meta.get("data_fingerprints"):   # another machine's rounding
                record = {**record, "data_fingerprints": other.get("data_fingerprints")}
            networks.append(net)
            records.append(record)
    if len(networks) == 1:
        raise ModelFileError(paths[0], "holds one network: an ensemble needs two or more (give the checkpoints or "
                                       "model files of other seeds too)")
    import lfgnss

    from .provenance import git_state

    now = _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")
    meta = {k: v for k, v in meta.items() if k != "ensemble"}
    meta = {**meta, "format_version": ENSEMBLE_FORMAT_VERSION, "created_utc": now,
            "versions": {**(meta.get("versions") or {}), "lfgnss": lfgnss.__version__, "numpy": np.__version__},
            "ensemble": {"combine": ENSEMBLE_COMBINE,
                         "exported": {"command": command, "cwd": str(Path.cwd()), "git": git_state(),
                                      "created_utc": now},
                         "members": records, **({"grown_from": grown_from} if grown_from else {})}}
    return _write_model_file(out_path, params, normaliser, meta, members=networks[1:])


def source_file(source: str | Path) -> Path:
    """An ensemble source as a path: a bundled model's name (``"berlin-pp"``) is its model file."""
    path = Path(source)
    return model_path(path) if not path.exists() and may_name_a_bundled_model(path) else path


def _source_networks(path: Path) -> tuple[list[tuple[dict[str, np.ndarray], Normaliser, dict, dict]], dict | None]:
    """Each network of an ensemble source (a checkpoint, or a model file's members): its weights, normaliser, the
    metadata it is checked by and its ``ensemble.members`` record (checkpoint, seed, epoch, validation RMSE,
    provenance; a model file's members keep theirs, and one not yet from a model file adds ``model_file`` and
    ``model_file_sha256_16``: the file it came from, which a grown ensemble written in place replaces); and, for a
    model file, its ``ensemble.grown_from`` record (path, SHA-256, networks, how it was put together)."""
    if not str(path).endswith(".npz"):
        params, normaliser, meta = _checkpoint_contents(path)
        return [(params, normaliser, meta, {"checkpoint": str(path), "seed": (meta.get("config") or {}).get("seed"),
                                            "epoch": meta.get("epoch"), "val_rmse_3d_m": meta.get("val_rmse_3d_m"),
                                            "provenance": meta.get("provenance")})], None
    model = load_model(path)
    meta = json.loads(json.dumps(model.metadata, default=_json_default))
    records = ensemble_members(meta) or [{"checkpoint": None, "seed": (meta.get("config") or {}).get("seed"),
                                          "epoch": meta.get("epoch"), "val_rmse_3d_m": meta.get("val_rmse_3d_m"),
                                          "provenance": meta.get("provenance")}]
    sha = file_hash(path, content=False)
    ensemble = meta.get("ensemble") or {}
    grown = {"model_file": str(path), "sha256_16": sha, "networks": len(model.members),
             "exported": ensemble.get("exported"),
             **({"grown_from": ensemble["grown_from"]} if ensemble.get("grown_from") else {})}
    return [({k: v.astype(np.float32) for k, v in net.items()}, model.normaliser, meta,
             record if record.get("model_file") else {**record, "model_file": str(path), "model_file_sha256_16": sha})
            for net, record in zip(model.members, records)], grown


#: Training settings that name files rather than say what was trained: the files' contents are compared instead
#: (``data_fingerprints``, ``init_model``'s SHA-256), so runs started from other folders still make one ensemble.
_MEMBER_PATH_KEYS = ("train.init", "data.register")


def _is_last_pt(record: dict) -> bool:
    """Whether an ensemble member's network is a ``last.pt``: its run's latest epoch, which ``train.select`` (the
    choice between ``best.pt`` and ``last.pt`` for ``model.npz``) does not choose, unlike a ``best.pt``'s."""
    return Path(str(record.get("checkpoint") or "")).name == "last.pt"


def _values_text(here: object, there: object) -> str:
    """Two differing settings for a one-line message: ``here: VALUE; there: VALUE`` (a list as its items)."""
    def text(value: object) -> str:
        return shortened(", ".join(map(str, value)) if isinstance(value, list) else repr(value), 200)

    return f"here: {text(here)}; there: {text(there)}"


def _member_difference(meta: dict, normaliser: Normaliser, other: dict, other_normaliser: Normaliser,
                       free: tuple[str, ...] = ()) -> tuple[str, str] | None:
    """The first setting in which a would-be ensemble member (``other``) differs from the first one, and its values
    in words (``_values_text``, the member's first), or None; training settings in ``free`` may differ too."""
    from .train import DEFAULT_CONFIG, _flat, _merge_free

    mine, theirs = list(other_normaliser.feature_names), list(normaliser.feature_names)
    if mine != theirs:
        return "feature_names", _values_text(mine, theirs)
    if set(normaliser.signed_log) != set(other_normaliser.signed_log):
        return "the normaliser's signed_log", _values_text(list(other_normaliser.signed_log) or ["none"],
                                                           list(normaliser.signed_log) or ["none"])
    if not normaliser.same_as(other_normaliser):
        return "the normaliser (the training data's feature statistics)", "the feature means or stds"

    def same(a: object, b: object) -> bool:
        return json.dumps(a, default=_json_default, sort_keys=True) == json.dumps(b, default=_json_default,
                                                                                  sort_keys=True)

    def first_change(a: object, b: object) -> str:
        """``KEY: VALUES`` of the first key two tables differ in (the values alone for others than tables)."""
        if not (isinstance(a, dict) and isinstance(b, dict)):
            return _values_text(b, a)
        flat_a, flat_b = _flat(a), _flat(b)
        keys = sorted(k for k in flat_a.keys() | flat_b.keys() if not same(flat_a.get(k), flat_b.get(k)))
        if not keys:                                    # an empty table against none
            return _values_text(b, a)
        return f"{keys[0]}: {_values_text(flat_b.get(keys[0], 'unset'), flat_a.get(keys[0], 'unset'))}"

    for key in ("model", "ekf_config", "n_systems"):
        if not same(meta.get(key), other.get(key)):
            return key, first_change(meta.get(key), other.get(key))
    if not _same_data(meta, other):
        prints, others = meta.get("data_fingerprints") or [], other.get("data_fingerprints") or []
        return "data_fingerprints", f"other training or validation data: {len(others)} sequence(s) here, " \
                                    f"{len(prints)} there"
    init, other_init = meta.get("init_model") or {}, other.get("init_model") or {}
    if init.get("sha256_16") != other_init.get("sha256_16"):
        return "init_model (the model fine-tuning started from)", _values_text(other_init.get("path"),
                                                                               init.get("path"))
    a, b = (_flat(_merge_free(DEFAULT_CONFIG, m.get("config") or {})) for m in (meta, other))
    changed = sorted(k for k in a.keys() | b.keys()
                     if k not in ENSEMBLE_FREE + _MEMBER_PATH_KEYS + free and not same(a.get(k), b.get(k)))
    return (f"config {changed[0]}", _values_text(b.get(changed[0], "unset"), a.get(changed[0], "unset"))) \
        if changed else None


def _same_data(meta: dict, other: dict) -> bool:
    """Whether two networks were trained on the same data: the same sequences' fingerprints or, for runs on another
    machine, whose features differ in rounding and so in their hashes, the same sequences (names, splits, epochs) of
    the same input files (``source_files``' SHA-256; the normalisers are compared too, ``Normaliser.same_as``)."""
    prints, others = meta.get("data_fingerprints") or [], other.get("data_fingerprints") or []
    if prints == others:
        return True

    def unhashed(fingerprints: list) -> list:
        return [{k: v for k, v in p.items() if k != "sha256_16"} for p in fingerprints]

    return any((meta.get("source_files") or {}).values()) and meta.get("source_files") == other.get("source_files") \
        and unhashed(prints) == unhashed(others)


def _checkpoint_contents(checkpoint_path: str | Path) -> tuple[dict[str, np.ndarray], Normaliser, dict]:
    """A training checkpoint's weights (float32), normaliser and model-file metadata."""
    import pickle

    import torch

    import lfgnss

    from .train import read_checkpoint     # train imports this module

    try:
        ckpt = read_checkpoint(checkpoint_path)
        if not isinstance(ckpt, dict):
            raise ValueError(f"it holds a {type(ckpt).__name__}, not a checkpoint's dict")
        state = ckpt["model"]
        hparams = ckpt["model_hparams"]
        normaliser = Normaliser.from_dict(ckpt["normaliser"])
        params = {name: t.detach().cpu().numpy().astype(np.float32) for name, t in state.items()}
    except (OSError, RuntimeError, KeyError, ValueError, TypeError, AttributeError, EOFError,
            pickle.UnpicklingError) as exc:
        reason = str(exc) if str(exc).startswith("not a torch file") else f"{type(exc).__name__}: {exc}"
        raise ModelFileError(checkpoint_path, f"not a usable training checkpoint ({reason})") from exc
    history = ckpt.get("history") or []
    row = next((h for h in history if h.get("epoch") == ckpt.get("epoch")), {})
    meta = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "feature_names": list(normaliser.feature_names),
        "model": hparams,
        "layer_norm_eps": 1e-5,
        "parameters": {k: list(v.shape) for k, v in params.items()},
        "normaliser": normaliser.to_dict(),
        "config": ckpt.get("config"),
        "ekf_config": ckpt.get("ekf_config"),
        "n_systems": ckpt.get("n_systems"),
        "data_fingerprints": ckpt.get("data_fingerprints", []),
        "data_spans": ckpt.get("data_spans", []),
        "source_files": ckpt.get("source_files", {}),
        "init_model": ckpt.get("init_model"),
        "config_file": ckpt.get("config_file"),
        "provenance": ckpt.get("provenance"),
        "epoch": ckpt.get("epoch"),
        "val_rmse_3d_m": row.get("val_rmse_3d_m"),
        "versions": {"lfgnss": lfgnss.__version__, "torch": torch.__version__, "numpy": np.__version__},
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }
    return params, normaliser, meta


def _write_model_file(out_path: str | Path, params: dict[str, np.ndarray], normaliser: Normaliser, meta: dict,
                      members: list[dict[str, np.ndarray]] | None = None) -> Path:
    """The model file's arrays (weights as float32; ``members``: an ensemble's further networks) written to
    ``out_path`` atomically (a kill mid-write, or a written file that does not read back, keeps the file that was
    there)."""
    arrays = {f"param/{k}": np.asarray(v, np.float32) for k, v in params.items()}    # the format's float32
    for i, member in enumerate(members or [], start=1):
        arrays.update({f"member{i}/param/{k}": np.asarray(v, np.float32) for k, v in member.items()})
    arrays["normaliser_mean"] = normaliser.mean.astype(np.float64)
    arrays["normaliser_std"] = normaliser.std.astype(np.float64)
    arrays["metadata"] = np.array(json.dumps(meta, default=_json_default))

    out = Path(out_path)

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
        try:
            load_model(tmp)                         # before it replaces anything (out may be a source)
        except ModelFileError as exc:
            raise ModelFileError(out, f"the file written does not read back, so it was not written ({exc.reason})") \
                from exc

    if out.is_dir():
        raise IsADirectoryError(errno.EISDIR, "a folder, not a model file to write", str(out))
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        replace_atomically(out, write)
    except OSError as exc:                          # name the file asked for, not the temporary one beside it
        blocked = next((p for p in out.parents if p.is_file()), None)     # mkdir's "File exists" says too little
        why = f"{blocked} is a file, not a folder" if blocked is not None else exc.strerror or exc
        raise OSError(exc.errno, f"cannot write the model file ({why})", str(out)) from exc
    return out


def _json_default(obj):
    if isinstance(obj, (np.floating, np.integer)):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    return str(obj)


# --------------------------------------------------------------------------- reading / inference

def _softplus(x: np.ndarray) -> np.ndarray:
    return np.logaddexp(0.0, x)


def _linear(x: np.ndarray, p: dict, name: str) -> np.ndarray:
    return x @ p[f"{name}.weight"].T + p[f"{name}.bias"]


class LfgnssModel:
    """A loaded model file: numpy forward pass of ``learning.network.LfgnssNet`` plus its normaliser.

    Attributes
    ----------
    path : str
    feature_names : tuple of str
    metadata : dict
    normaliser : Normaliser
    """

    def __init__(self, path: str, params: dict[str, np.ndarray], normaliser: Normaliser, metadata: dict,
                 members: list[dict[str, np.ndarray]] | None = None) -> None:
        self.path = path
        self.params = {k: v.astype(np.float64) for k, v in params.items()}
        #: every network's parameters, ``params`` first; more than one for an ensemble file (``export_ensemble``)
        self.members = [self.params] + [{k: v.astype(np.float64) for k, v in m.items()} for m in members or []]
        self.normaliser = normaliser
        self.metadata = metadata
        self.feature_names = tuple(normaliser.feature_names)
        m = model_settings(metadata)
        self.n_heads = int(m["n_heads"])
        self.d_model = int(m["d_model"])
        self.n_hidden = len(m["hidden"])
        self.r_floor_m2 = float(m["r_floor_m2"])
        self.r_scale_m2 = float(m.get("r_scale_m2", 1.0))
        self.r_prior = m.get("r_prior")
        self.compensation = bool(m.get("compensation", True))
        #: True: the network reads the EKF's prior innovations (``predict``'s ``innovation``), epoch by epoch.
        self.online = bool(m["innovation"])
        self.eps = float(metadata.get("layer_norm_eps", 1e-5))

    def __repr__(self) -> str:
        return f"LfgnssModel({self.path!r}, features={list(self.feature_names)})"

    def predict(self, features: np.ndarray, mask: np.ndarray, innovation: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
        """Noise for raw (un-normalised) features.

        Parameters
        ----------
        features : (..., N, d) raw features in ``feature_names`` order
        mask : (..., N) bool, True for valid satellites
        innovation : (..., N) ``lfgnss.features.innovation_feature`` of the prior innovations; required if and
            only if the model is ``online``

        Returns
        -------
        r_m2, vc_m : (..., N) float64; ``PAD_R_M2`` and 0 in padded slots.
        """
        features = np.asarray(features, dtype=np.float64)
        mask = np.asarray(mask, bool)
        d = len(self.feature_names)
        if features.shape[:-1] != mask.shape or features.shape[-1] != d:
            raise ValueError(f"{self.path}: features {features.shape} / mask {mask.shape} do not match (..., N, {d})")
        if (innovation is not None) != self.online or (innovation is not None and np.shape(innovation) != mask.shape):
            raise ValueError(f"{self.path}: this model {'needs' if self.online else 'takes no'} innovations shaped "
                             f"like the mask {mask.shape}")
        bad = mask[..., None] & ~np.isfinite(features)
        if bad.any():   # the normaliser would put the training mean there and the network would run on it unseen
            first = tuple(np.argwhere(bad)[0])
            *where, slot, k = first
            epoch = f"epoch {where[-1]}, " if where else ""
            raise ValueError(f"{self.path}: feature {self.feature_names[k]!r} is {features[first]} at {epoch}satellite "
                             f"slot {slot} ({int(bad.any(-1).sum())} satellite slot(s) in all); give finite features "
                             "on every masked-in slot (or mask the slot out)")
        lead, n = mask.shape[:-1], mask.shape[-1]
        if n == 0:                  # no satellite slot: nothing to run the network on (reshape(-1, 0) is ambiguous)
            return np.full(mask.shape, PAD_R_M2), np.zeros(mask.shape)
        x = self.normaliser.apply(features, mask)
        if self.online:
            x = np.concatenate([x, np.where(mask, innovation, 0.0)[..., None]], -1)
        x = x.reshape(-1, n, d + self.online)
        m = mask.reshape(-1, n)
        # in chunks of epochs: the attention scores alone are (M, H, N, N), ~0.3 MB an epoch at N = 36
        r, vc = np.empty(m.shape), np.empty(m.shape)
        for s in range(0, m.shape[0], PREDICT_CHUNK_EPOCHS):
            rows = slice(s, s + PREDICT_CHUNK_EPOCHS)
            r[rows], vc[rows] = self._forward(x[rows], m[rows])
        r = np.where(m, r, PAD_R_M2).reshape(*lead, n)
        vc = np.where(m, vc, 0.0).reshape(*lead, n)
        return r, vc

    def _forward(self, x: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The network(s) on normalised inputs x (M, N, d) with mask m (M, N): (r_m2, vc_m), each (M, N), pads unset;
        an ensemble's members combined as ``learning.network.combine_members`` does."""
        if len(self.members) == 1:
            return self._network(x, m, self.params)
        outs = [self._network(x, m, p) for p in self.members]
        return np.exp(np.log(np.stack([o[0] for o in outs])).mean(0)), np.stack([o[1] for o in outs]).mean(0)

    def _network(self, x: np.ndarray, m: np.ndarray, p: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """One network with parameters ``p`` on x (M, N, d), mask m (M, N): (r_m2, vc_m), each (M, N)."""
        n = m.shape[-1]
        # h0 = x W_e^T + b_e
        h0 = _linear(x, p, "embed")
        # multi-head self-attention, keys of padded slots masked (all slots if the epoch has none)
        empty = ~m.any(axis=-1, keepdims=True)
        key_ok = m | empty                                             # (M, N)
        qkv = h0 @ p["attention.in_proj_weight"].T + p["attention.in_proj_bias"]
        q, k, v = np.split(qkv, 3, axis=-1)
        hd = self.d_model // self.n_heads

        def heads(a: np.ndarray) -> np.ndarray:                       # (M, N, D) -> (M, H, N, hd)
            return a.reshape(a.shape[0], n, self.n_heads, hd).transpose(0, 2, 1, 3)

        scores = heads(q) @ heads(k).transpose(0, 1, 3, 2) / np.sqrt(hd)     # (M, H, N, N)
        scores = np.where(key_ok[:, None, None, :], scores, -np.inf)
        scores = scores - scores.max(axis=-1, keepdims=True)
        weights = np.exp(scores)
        weights /= weights.sum(axis=-1, keepdims=True)
        attn = (weights @ heads(v)).transpose(0, 2, 1, 3).reshape(-1, n, self.d_model)
        attn = _linear(attn, p, "attention.out_proj")
        # h1 = LayerNorm(h0 + attn)
        h = h0 + attn
        mu = h.mean(axis=-1, keepdims=True)
        var = h.var(axis=-1, keepdims=True)
        h = (h - mu) / np.sqrt(var + self.eps) * p["norm.weight"] + p["norm.bias"]
        # MLP with ReLU, then head [o_R, o_v]
        for i in range(self.n_hidden):
            h = np.maximum(_linear(h, p, f"mlp.{2 * i}"), 0.0)
        o = _linear(h, p, "head")
        if self.r_prior is None:
            r = self.r_scale_m2 * _softplus(o[..., 0]) + self.r_floor_m2
        else:  # learned factor on the hand-set C/N0-elevation variance (learning.network.prior_variance)
            pr = self.r_prior
            cn0 = x[..., pr["cn0_index"]] * pr["cn0_std"] + pr["cn0_mean"]
            el = x[..., pr["el_index"]] * pr["el_std"] + pr["el_mean"]
            prior = cn0_elevation_variance_m2(cn0, el, floor_m=pr["floor_m"], cn0_scale_m2=pr["cn0_scale_m2"],
                                              elevation_power=pr["elevation_power"], el_min_rad=pr["el_min_rad"])
            r = prior * _softplus(o[..., 0]) / np.log(2.0) + self.r_floor_m2
        vc = o[..., 1] if self.compensation else np.zeros_like(r)
        return r, vc

    def features(self, sequence: Sequence) -> np.ndarray:
        """(T, N, d) raw features of ``sequence`` in ``feature_names`` order."""
        try:
            return select_features(sequence, self.feature_names)
        except ValueError as exc:
            raise ValueError(f"{self.path}: {exc}") from exc

    def __call__(self, sequence: Sequence) -> tuple[np.ndarray, np.ndarray]:
        """(r_m2, vc_m), each (T, N), for ``sequence``: a NoiseModel (``online``: those its EKF run asked the network
        for, R as the network gave it: switched-off slots stay off, and the filter's GLONASS factor is not in it; that
        run's warnings on R are left to the estimator given it, which judges the same R under its own name)."""
        if self.online:
            from estimators.ekf import LfgnssEkf

            ekf = LfgnssEkf(self)
            ekf._judges_noise = False
            info = ekf.solve(sequence).info
            return info["noise_r_m2"], info["vc_m"]
        return self.predict(self.features(sequence), sequence.mask)


#: Model settings added after files were first written, with the value older files were trained with.
OLD_FILE_MODEL_DEFAULTS = {"innovation": False}   # model.innovation, session 13


def model_settings(metadata: dict) -> dict:
    """A model file's ``model`` settings (``LfgnssNet.hyperparameters``), older files' missing ones filled in."""
    return OLD_FILE_MODEL_DEFAULTS | metadata["model"]


#: Least ``model.r_floor_m2`` [m^2] (training and model files alike): the plug-in EKF refuses an update with R near
#: 1e-10 m^2 as numerically singular (estimators.ekf), and the torch EKF raised torch.linalg.LinAlgError at 1e-12 m^2;
#: loss.r_weight's ln R needs R > 0.
MIN_R_FLOOR_M2 = 1.0e-6
_REQUIRED_META = ("format", "format_version", "feature_names", "model", "parameters", "normaliser")
_REQUIRED_MODEL = ("d_model", "n_heads", "hidden", "r_floor_m2")
_PRIOR_KEYS = ("cn0_index", "el_index", "cn0_mean", "cn0_std", "el_mean", "el_std", "floor_m", "cn0_scale_m2",
               "elevation_power", "el_min_rad")


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and abs(value) <= sys.float_info.max


def _is_count(value, minimum: int = 1) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= minimum


def _check_metadata(path: str, meta: dict) -> None:
    """Types and values of the metadata the forward pass and the EKF use; ModelFileError naming file and key."""
    def fail(key: str, need: str, value) -> None:
        shown = {list: "a list", dict: "a table"}.get(type(value)) or f"{' '.join(repr(value).split())!s:.60}"
        raise ModelFileError(path, f"metadata {key} must be {need}, not {shown}")

    for key in ("model", "parameters", "normaliser"):
        if not isinstance(meta[key], dict):
            fail(key, "a table", meta[key])
    for name, shape in meta["parameters"].items():
        if not (isinstance(shape, list) and all(_is_count(n, 0) for n in shape)):
            fail(f"parameters.{name}", "a list of array dimensions", shape)
    m = model_settings(meta)
    missing = [k for k in _REQUIRED_MODEL if k not in m]
    if missing:
        raise ModelFileError(path, f"metadata model.{missing[0]} missing (needs {', '.join(_REQUIRED_MODEL)})")
    d_model, n_heads, prior = m["d_model"], m["n_heads"], m.get("r_prior")
    checks = [("d_model", _is_count(d_model), "an integer >= 1"),
              ("n_heads", _is_count(d_model) and _is_count(n_heads) and d_model % n_heads == 0,
               f"an integer >= 1 dividing d_model {d_model}"),
              ("hidden", isinstance(m["hidden"], list) and all(_is_count(h) for h in m["hidden"]),
               "a list of integers >= 1"),
              ("r_floor_m2", _is_number(m["r_floor_m2"]) and m["r_floor_m2"] >= MIN_R_FLOOR_M2,
               f"a finite number >= {MIN_R_FLOOR_M2:g} (learning.train's least)"),
              ("r_scale_m2", _is_number(m.get("r_scale_m2", 1.0)) and m.get("r_scale_m2", 1.0) > 0,
               "a finite number > 0"),
              ("compensation", isinstance(m.get("compensation", True), bool), "true or false"),
              ("innovation", isinstance(m["innovation"], bool), "true or false"),
              ("r_prior", prior is None or isinstance(prior, dict), "a table or null")]
    for key, ok, need in checks:
        if not ok:
            fail(f"model.{key}", need, m.get(key))
    d = len(meta["feature_names"])
    for key in _PRIOR_KEYS if prior is not None else ():
        value = prior.get(key)
        if key.endswith("_index") and not (_is_count(value, 0) and value < d):
            fail(f"model.r_prior.{key}", f"a feature index below {d}", value)
        if not _is_number(value):
            fail(f"model.r_prior.{key}", "a finite number", value)
    eps = meta.get("layer_norm_eps", 1e-5)
    if not (_is_number(eps) and eps > 0):
        fail("layer_norm_eps", "a finite number > 0", eps)
    stored = meta.get("ekf_config")
    if stored is not None and not isinstance(stored, dict):
        fail("ekf_config", "a table or null", stored)
    from estimators.models import EkfConfig, stored_ekf_config   # the filter settings as the EKF reads them

    known = {f.name for f in dataclasses.fields(EkfConfig)}
    for key, value in (stored or {}).items():
        if key in known and not (value is None or isinstance(value, (int, float))):
            fail(f"ekf_config.{key}", "a number or null", value)
    try:
        stored_ekf_config(stored)
    except (TypeError, ValueError) as exc:
        reason = " ".join(str(exc).split()).removeprefix("estimators/models.py: ")
        raise ModelFileError(path, f"metadata ekf_config: {reason}") from exc


def _parameter_shapes(m: dict, n_inputs: int) -> dict[str, list[int]]:
    """The shape of every tensor the forward pass reads, from the ``model`` settings."""
    dm = m["d_model"]
    shapes = {"embed.weight": [dm, n_inputs], "embed.bias": [dm], "attention.in_proj_weight": [3 * dm, dm],
              "attention.in_proj_bias": [3 * dm], "attention.out_proj.weight": [dm, dm],
              "attention.out_proj.bias": [dm], "norm.weight": [dm], "norm.bias": [dm]}
    width = dm
    for i, h in enumerate(m["hidden"]):
        shapes[f"mlp.{2 * i}.weight"], shapes[f"mlp.{2 * i}.bias"] = [h, width], [h]
        width = h
    shapes["head.weight"], shapes["head.bias"] = [2, width], [2]
    return shapes


def load_model(path: str | Path, expected_features: Iterable[str] | None = None) -> LfgnssModel:
    """Read and check a model file written by ``export_model``, or a bundled one by name (``"hk-tst-2019"``).

    Raises
    ------
    ModelFileError
        (a ``ValueError``) naming the file and the reason: unreadable / truncated / corrupt file,
        another format or version, metadata of the wrong type or value (naming the key), missing or
        mis-shaped arrays, features that this version of ``lfgnss.features`` cannot compute, features
        other than ``expected_features`` (names and order), or a network that does not run on a test input.
    """
    path = str(model_path(path))
    try:
        with open(path, "rb") as fh:
            magic = fh.read(4)
        arrays = None
        if magic.startswith(b"PK"):
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: np.asarray(z[k]) for k in z.files}
    except FileNotFoundError as exc:
        bundled = bundled_models()
        names = list(bundled)
        # a bundled model's file name (docs/results.md lists them) is not where that file is
        by_file = {f.name: name for name, f in bundled.items()} | {f.stem: name for name, f in bundled.items()}
        if Path(path).name in by_file:
            hint = f"; the bundled {bundled[by_file[Path(path).name]].name} is named {by_file[Path(path).name]!r}"
        elif may_name_a_bundled_model(path):
            close = closest_name(Path(path).name, names)
            hint = f" or bundled model ({', '.join(names)}){f'; did you mean {close!r}?' if close else ''}"
        else:
            hint = ""
        raise ModelFileError(path, f"no such model file{hint}") from exc
    except IsADirectoryError as exc:
        raise ModelFileError(path, "a folder, not a model file") from exc
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as exc:
        if "allow_pickle" in str(exc):
            raise ModelFileError(path, "not an lfgnss model file (it holds pickled Python objects)") from exc
        raise ModelFileError(path, f"truncated or corrupt model file ({type(exc).__name__}: {exc})") from exc
    if arrays is None:
        raise ModelFileError(path, "not an lfgnss model file (not an .npz archive)" if magic else "empty file")
    if "metadata" not in arrays:
        if any(name.endswith("data.pkl") for name in arrays):       # torch.save's zip: a learning.train checkpoint
            raise ModelFileError(path, "a training checkpoint, not a model file: export it first (python -m "
                                       f"learning.export {path} model.npz)")
        raise ModelFileError(path, "not an lfgnss model file (no metadata)")
    try:
        meta = json.loads(str(arrays["metadata"]))
    except (ValueError, TypeError) as exc:
        raise ModelFileError(path, f"metadata is not valid JSON ({exc})") from exc
    if not isinstance(meta, dict):
        raise ModelFileError(path, f"not an {FORMAT_NAME} file (metadata is a JSON {type(meta).__name__}, not a table)")
    missing = [k for k in _REQUIRED_META if k not in meta]
    if missing or meta.get("format") != FORMAT_NAME:
        raise ModelFileError(path, f"not an {FORMAT_NAME} file (format {meta.get('format')!r}, missing {missing})")
    if meta["format_version"] not in (FORMAT_VERSION, ENSEMBLE_FORMAT_VERSION):
        raise ModelFileError(path, f"format version {meta['format_version']!r} is not supported "
                                   f"(this lfgnss reads versions {FORMAT_VERSION} and {ENSEMBLE_FORMAT_VERSION})")
    n_members = _ensemble_size(path, meta)
    names = meta["feature_names"]
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise ModelFileError(path, f"feature_names is not a list of names ({names!r:.80})")
    unknown = [n for n in names if n not in AVAILABLE_FEATURES]
    if unknown:  # the same words as the CLI check in lfgnss.solve
        raise ModelFileError(path, f"the model needs feature(s) {', '.join(unknown)} that this lfgnss cannot compute "
                                   f"(it computes {', '.join(AVAILABLE_FEATURES)})")
    _check_metadata(path, meta)
    members = []
    for prefix in ["", *(f"member{i}/" for i in range(1, n_members))]:
        params = {}
        for name, shape in meta["parameters"].items():
            arr = arrays.get(f"{prefix}param/{name}")
            if (arr is None or list(arr.shape) != list(shape) or arr.dtype.kind not in "fiu"
                    or not np.all(np.isfinite(arr))):
                raise ModelFileError(path, f"parameter {prefix + name!r} missing, mis-shaped or not finite")
            params[name] = arr
        members.append(params)
    listed = {f"member{i}" for i in range(1, n_members)}
    unlisted = sorted(k for k in arrays if k.startswith("member") and k.split("/")[0] not in listed)
    if unlisted:
        raise ModelFileError(path, f"array {unlisted[0]} belongs to no network its metadata lists "
                                   f"({n_members}; ensemble.members)")
    params = members[0]
    try:
        logged = meta["normaliser"].get("signed_log", [])
        if not (isinstance(logged, list) and all(isinstance(n, str) for n in logged)):
            raise ValueError(f"metadata normaliser.signed_log must be a list of feature names, not {logged!r:.60}")
        normaliser = Normaliser(tuple(meta["feature_names"]), arrays["normaliser_mean"], arrays["normaliser_std"],
                                tuple(logged))
    except (KeyError, ValueError, TypeError) as exc:
        reason = "normaliser_mean / normaliser_std are not numbers" if isinstance(exc, TypeError) else exc
        raise ModelFileError(path, f"bad normaliser ({reason})") from exc
    settings = model_settings(meta)
    prior = settings.get("r_prior")
    read = {normaliser.feature_names[prior[k]] for k in ("cn0_index", "el_index")} if prior else set()
    logged_read = sorted(read & set(normaliser.signed_log))
    if logged_read:
        raise ModelFileError(path, f"metadata normaliser.signed_log names {logged_read}, which the R prior "
                                   "(model.r_prior) reads in its own units")
    n_inputs = len(normaliser.feature_names) + settings["innovation"]
    shapes = _parameter_shapes(settings, n_inputs)
    absent = [k for k in shapes if k not in params]       # every member has the same names (meta["parameters"])
    if absent:
        layers = f" (model.hidden is {settings['hidden']})" if any(k.startswith("mlp.") for k in absent) else ""
        raise ModelFileError(path, f"parameters {absent} missing{layers}")
    if params["embed.weight"].shape[1] != n_inputs:
        raise ModelFileError(path, f"embedding takes {params['embed.weight'].shape[1]} inputs but "
                                   f"{n_inputs} are named")
    for name, want in shapes.items():
        if list(params[name].shape) != want:
            raise ModelFileError(path, f"parameter {name!r} is {list(params[name].shape)} but model.d_model "
                                       f"{settings['d_model']} and model.hidden {settings['hidden']} need {want}")
    if expected_features is not None and tuple(expected_features) != tuple(normaliser.feature_names):
        raise ModelFileError(path, f"model features {list(normaliser.feature_names)} do not match the expected "
                                   f"{list(expected_features)}")
    try:  # backstop: one epoch of two satellites at the normaliser mean must give usable noise
        model = LfgnssModel(path, params, normaliser, meta, members[1:])
        with np.errstate(all="ignore"):
            r, vc = model.predict(np.tile(normaliser.mean, (1, 2, 1)), np.ones((1, 2), bool),
                                  np.zeros((1, 2)) if model.online else None)
    except Exception as exc:  # noqa: BLE001 -- any failure here is the file's
        raise ModelFileError(path, f"the network does not run ({type(exc).__name__}: "
                                   f"{' '.join(str(exc).split())})") from exc
    if not (np.all(np.isfinite(r)) and np.all(r > 0) and np.all(np.isfinite(vc))):
        raise ModelFileError(path, "the network gives non-finite or non-positive noise on a test input")
    return model


def _ensemble_size(path: str, meta: dict) -> int:
    """How many networks a model file holds: 1 for version 1, its ``ensemble.members`` (>= 2) for version 2."""
    ensemble = meta.get("ensemble")
    if meta["format_version"] == FORMAT_VERSION:
        if ensemble is not None:
            raise ModelFileError(path, f"metadata ensemble in a format version {FORMAT_VERSION} file (ensembles "
                                       f"are version {ENSEMBLE_FORMAT_VERSION})")
        return 1
    members = ensemble.get("members") if isinstance(ensemble, dict) else None
    if not (isinstance(members, list) and len(members) >= 2 and all(isinstance(m, dict) for m in members)):
        raise ModelFileError(path, "metadata ensemble.members must list two or more networks in a format version "
                                   f"{ENSEMBLE_FORMAT_VERSION} (ensemble) file")
    return len(members)


def ensemble_members(metadata: dict) -> list[dict]:
    """An ensemble file's ``ensemble.members`` records (seed, epoch, ... of each network); [] for a single network."""
    return (metadata.get("ensemble") or {}).get("members") or []


def trained_smoothed(metadata: dict) -> bool:
    """Whether a model file was trained and selected on RTS-smoothed positions (``train.smooth = true``): it is meant
    for the EKF with its smoother (``smooth=True``, ``lfgnss.solve --smooth``)."""
    return ((metadata.get("config") or {}).get("train") or {}).get("smooth") is True


def trained_systems(metadata: dict) -> str | None:
    """The constellations (letters, GCERJ order) of the data a model file was trained and selected on, from its
    ``data_spans`` and those of the model it was fine-tuned from (``init_model``, and its own); None where one of them
    does not record them (trained before session 50, as the bundled models)."""
    from lfgnss.constants import SYSTEMS

    letters: set[str] = set()
    record = metadata
    while isinstance(record, dict):     # a fine-tuned network keeps what its start learnt of other constellations
        spans = [s for s in record.get("data_spans") or [] if isinstance(s, dict)]
        if not spans or not all(isinstance(s.get("systems"), str) for s in spans):
            return None
        letters |= set("".join(s["systems"] for s in spans))
        record = record.get("init_model")
    return "".join(c for c in SYSTEMS if c in letters)


def member_epochs(metadata: dict) -> list:
    """The training epoch of each network in a model file (one for a single network)."""
    return [m.get("epoch") for m in ensemble_members(metadata)] or [metadata.get("epoch")]


def refilter_model(source_path: str | Path, out_path: str | Path, changes: dict, command: str | None = None) -> Path:
    """Write a model file whose network runs in a filter with some EKF settings (``ekf_config``) changed.

    ``source_path`` is a model file (``.npz``) or a training checkpoint (``best.pt`` / ``last.pt``). ``changes`` maps
    ``estimators.EkfConfig`` field names to new values (a ValueError names an unknown or bad one, or a setting that
    already has that value). The file keeps its training ``config`` and any ``ekf_config`` keys this version does not
    know; the change, with the settings before and after, ``source_path``, ``command``, the git state and the package
    versions, is appended to its ``refilter`` record, which ``--show`` prints. Use it for a filter setting chosen by
    rescoring a recipe's cross-validation folds (``learning.crossval --reuse``) rather than by retraining.
    """
    import lfgnss
    from estimators.models import EkfConfig, stored_ekf_config

    from .provenance import git_state

    if str(source_path).endswith(".npz"):
        source = load_model(source_path)
        params, normaliser, members = source.params, source.normaliser, source.members[1:]
        meta = json.loads(json.dumps(source.metadata, default=_json_default))
    else:
        (params, normaliser, meta), members = _checkpoint_contents(source_path), []
    known = {f.name for f in dataclasses.fields(EkfConfig)}
    unknown = sorted(set(changes) - known)
    if unknown or not changes:
        raise ValueError(f"no EKF setting {', '.join(unknown)} (EkfConfig has {', '.join(sorted(known))})" if unknown
                         else "no EKF setting to change")
    stored = meta.get("ekf_config") or {}
    before = stored_ekf_config(stored)
    floats = {f.name for f in dataclasses.fields(EkfConfig) if "float" in str(f.type)}
    changes = {k: float(v) if k in floats and type(v) is int else v for k, v in changes.items()}   # TOML's 4 is 4.0
    same = sorted(k for k, v in changes.items() if getattr(before, k) == v)
    if same:
        raise ValueError(", ".join(f"{k} is already {getattr(before, k)!r}" for k in same) + " in this model's filter")
    after = dataclasses.replace(before, **changes)             # EkfConfig checks the values
    meta["ekf_config"] = {**stored, **dataclasses.asdict(after)}
    meta["refilter"] = list(meta.get("refilter") or []) + [{
        "changes": {k: [getattr(before, k), getattr(after, k)] for k in sorted(changes)},
        "source": str(source_path), "command": command, "git": git_state(),
        "versions": {"lfgnss": lfgnss.__version__, "numpy": np.__version__},
        "created_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")}]
    return _write_model_file(out_path, params, normaliser, meta, members)   # out may be source_path itself


def refilter_lines(metadata: dict) -> list[str]:
    """``--show`` lines on a model file's filter changes after training (none for most files)."""
    lines = []
    for rec in metadata.get("refilter") or []:
        changed = ", ".join(f"{k} {a!r} -> {b!r}" for k, (a, b) in (rec.get("changes") or {}).items())
        lines.append(f"filter changed after training: {changed} ({rec.get('created_utc', '?')}, "
                     f"command: {rec.get('command') or '(called from Python, no command line)'})")
    return lines


# --------------------------------------------------------------------------- command line

def trained_on(metadata: dict) -> str:
    """The data a model file was trained on, e.g. 'berlin-pp (train)', 'berlin-pp (train), 3 seeds' (an ensemble) or
    '... (train), fine-tuned from X (train)'."""
    data = (metadata.get("config") or {}).get("data", {})
    trained = "+".join(data.get("datasets", [])) + f" ({data.get('train_split', 'train')})"
    init = metadata.get("init_model")
    members = len(ensemble_members(metadata))
    trained += f", {members} seeds" if members else ""
    return trained if not init else (f"{trained}, fine-tuned from {'+'.join(init.get('datasets', []))} "
                                     f"({init.get('train_split', 'train')})")


#: A training piece whose time span holds test epochs is the same drive when their truths' extents come within this
#: of each other [m]: the same file under another id, name or compression, or a co-located receiver.
SAME_PLACE_M = 1000.0


def truth_extent(truth_ecef_m: np.ndarray) -> tuple[np.ndarray, float | None]:
    """Median of (T, 3) truth positions [m] and the largest distance of one from it [m]; (NaNs, None) without truth."""
    truth = np.asarray(truth_ecef_m, float).reshape(-1, 3)
    truth = truth[np.all(np.isfinite(truth), axis=1)]
    if not len(truth):
        return np.full(3, np.nan), None
    centre = np.median(truth, axis=0)
    return centre, float(np.max(np.linalg.norm(truth - centre, axis=1)))


def _numbers(value: object, n: int) -> list[float] | None:
    """``value`` as a list of ``n`` finite numbers, or None (a record written by hand, or by an older lfgnss)."""
    ok = isinstance(value, list) and len(value) == n and all(_is_number(v) for v in value)
    return [float(v) for v in value] if ok else None


def _used_as(split: object, select: object) -> str:
    """How a model used a piece of the split named ``split``: validation selects the model (``train.select =
    "val"``, the default) or, with ``"last"``, is only scored (its schedule was chosen by cross-validation); the rest
    trains it."""
    if split not in ("val", "validation"):
        return "trained on"
    return "validated on" if select == "last" else "selected on"


def _select(record: dict) -> object:
    """A model record's ``train.select``: its config's (a model file's metadata) or its own (a ``train.init``
    record), else None."""
    train = (record.get("config") or {}).get("train") if isinstance(record.get("config"), dict) else None
    return train.get("select") if isinstance(train, dict) else record.get("select")


def seen_test_epochs(metadata: dict, dataset_id: str, test_time_gps_s: np.ndarray, test_truth_ecef_m: np.ndarray,
                     obs_hashes: Iterable[str] = (), epochs_word: str = "test epochs") -> list[str]:
    """Where a model (or a model it was fine-tuned from) was trained or selected on test epochs: a line for each piece
    of the model's own, one for each starting model (its pieces joined, after one "fine-tuned from ..." prefix).

    ``test_time_gps_s`` (T,) [s] and ``test_truth_ecef_m`` (T, 3) [m]: the test split's scored epochs. A training or
    validation piece (``data_spans``) counts when its time span holds test epochs and its truth's extent
    (``truth_extent``) comes within ``SAME_PLACE_M`` of theirs (a piece without truth counts by time alone). A record
    without spans (a model file of before session 49, or one fine-tuning started from) is checked only where another
    of its datasets reads one of the test dataset's observation files (``obs_hashes``: content SHA-256, 16 hex
    digits, ``lfgnss.paths.file_hashes``) and the record lists its ``source_files``: by that dataset's split bounds as
    registered now (``lfgnss.datasets.epochs_in_split``), else named as one that may hold test epochs. The lines
    call the epochs ``epochs_word`` (``lfgnss.solve``: the run's scored epochs).
    """
    from lfgnss.datasets import epochs_in_split

    times, hashes = np.asarray(test_time_gps_s, float), set(obs_hashes)
    centre, radius = truth_extent(test_truth_ecef_m)
    lines, record, via = [], metadata, ""
    while isinstance(record, dict):
        found: list[str] = []                   # this record's pieces: its own lines, one line for a starting model's
        select = _select(record)
        spans = [s for s in record.get("data_spans") or [] if isinstance(s, dict)]
        for span in spans:
            t, where = _numbers(span.get("gps_s"), 2), _numbers(span.get("place_ecef_m"), 3)
            n = int(np.sum((times >= t[0]) & (times <= t[1]))) if t else 0
            reach = SAME_PLACE_M + (radius or 0.0) + (span["radius_m"] if _is_number(span.get("radius_m")) else 0.0)
            near = where is None or radius is None or np.linalg.norm(np.asarray(where) - centre) <= reach
            if n and near:
                found.append(f"{_used_as(span.get('split'), select)} {span.get('sequence')} "
                             f"({span.get('dataset')} {span.get('split')}, GPS {t[0]:.1f}-{t[1]:.1f} s): {n} of "
                             f"{dataset_id}'s {times.size} {epochs_word}")
        files = record.get("source_files") or {}
        pieces = [] if spans else [p for p in record.get("data_fingerprints") or [] if isinstance(p, dict)]
        for ds in sorted({str(p.get("dataset", "")) for p in pieces}):
            if ds == dataset_id or not hashes & set((files.get(ds) or {}).values()):
                continue
            splits = sorted({str(p.get("split", "")) for p in pieces if p.get("dataset") == ds})
            hits = [epochs_in_split(ds, split, times) for split in splits]
            if None in hits:
                found.append(f"trained on dataset {ds}, which reads {dataset_id}'s observation file(s); the model "
                             "does not record which epochs (it predates data_spans), so its training may hold "
                             f"{epochs_word}")
            found += [f"{_used_as(split, select)} {ds} {split} (its split as registered now): {n} of "
                      f"{dataset_id}'s {times.size} {epochs_word}" for split, n in zip(splits, hits) if n]
        lines += ([f"{via}{', and '.join(found)}"] if via and found else found)
        record, bundled = _completed_init(record.get("init_model"))
        via = (f"{via}fine-tuned from {f'the bundled model {bundled!r}' if bundled else (record or {}).get('path')}, "
               "which was ")
    return lines


def _completed_init(record: object) -> tuple[object, str | None]:
    """(record, bundled name): a ``train.init`` record and, where its file is a bundled model (by content,
    ``sha256_16``), that model's name; a record that predates ``source_files`` and ``data_spans`` (the bundled
    hk-tst-2019 model's, of the transfer base) takes them from that file, so its training data are checked too."""
    if not isinstance(record, dict) or not isinstance(record.get("sha256_16"), str):
        return record, None
    bundled = bundled_models()
    digests = file_hashes(bundled.values(), content=False)             # by file name, as init records hash them
    name = next((n for n, path in bundled.items() if digests.get(path.name) == record["sha256_16"]), None)
    if name is None or record.get("source_files") or record.get("data_spans"):
        return record, name
    meta = load_model(bundled[name]).metadata
    return {**record, "source_files": meta.get("source_files") or {}, "data_spans": meta.get("data_spans") or [],
            "select": _select(meta)}, name


#: Where the bundled models' commands are written down (their files predate ``provenance``).
BUNDLED_README = "lfgnss/data/model/README.md"


def untrained_reason(model: LfgnssModel) -> str | None:
    """Why a model file holds no training (its exported epoch 0 of a run from scratch: the random network), or None.

    ``learning.train`` exports epoch 0 when no training epoch beat the untrained network on validation; started from
    ``train.init``, that epoch is the init model itself, which is trained, so only a run from scratch counts here.
    """
    meta = model.metadata
    epochs = member_epochs(meta)
    if 0 not in epochs or meta.get("init_model"):
        return None
    if len(epochs) > 1:
        return (f"member {epochs.index(0)} of this ensemble holds no training: it is epoch 0 of its run, the randomly "
                "initialised network that no training epoch beat on validation")
    return ("holds no training: it is epoch 0 of its run, the randomly initialised network that no training epoch "
            "beat on validation; its noise can give positions far worse than the plain EKF's")


def bundled_name(path: str | Path) -> str | None:
    """The name of the bundled model that the file ``path`` is (that file, or a byte-for-byte copy of it), else None."""
    try:
        here = Path(path).resolve()
        size = here.stat().st_size
        for name, bundled in bundled_models().items():
            if bundled.resolve() == here or (bundled.stat().st_size == size
                                             and bundled.read_bytes() == here.read_bytes()):
                return name
    except OSError:
        pass
    return None


def _null_keys(table: dict, prefix: str = "") -> list[str]:
    """Dotted keys of ``table``'s null (unset) entries, which TOML cannot hold."""
    out = []
    for key, value in table.items():
        if value is None:
            out.append(prefix + key)
        elif isinstance(value, dict):
            out += _null_keys(value, f"{prefix}{key}.")
    return out


def _without_nulls(value: object) -> object:
    """``value`` with the null entries of its tables left out (as its TOML reads back)."""
    if isinstance(value, dict):
        return {k: _without_nulls(v) for k, v in value.items() if v is not None}
    return value


def config_text(model: LfgnssModel) -> str:
    """The training configuration stored in a model file as TOML (``learning.train --config`` reads it), or as JSON
    where TOML cannot hold it exactly; ModelFileError if the file records none."""
    import tomllib

    import tomli_w

    config = model.metadata.get("config")
    if not isinstance(config, dict):
        raise ModelFileError(model.path, "no training configuration is recorded in this model file")
    nulls = _null_keys(config)
    members = len(model.members)
    head = [f"# The training configuration stored in {model.path}",
            *([f"# (its first network's: the file is an ensemble of {members} runs of this configuration that differ "
               "in train seed only)"] if members > 1 else []),
            "# (as learning.train ran it: defaults, --set, and a train.init model's network and filter included)",
            *([f"# not set (null: the default): {', '.join(nulls)}"] if nulls else [])]
    try:
        text = "\n".join(head) + "\n" + tomli_w.dumps(_without_nulls(config))
        if tomllib.loads(text) == _without_nulls(config):
            return text
    except (TypeError, ValueError):               # ValueError: TOMLDecodeError
        pass
    return json.dumps(config, indent=2, default=_json_default) + "\n"


def describe_model(model: LfgnssModel) -> list[str]:
    """Readable lines on a model file: data, epoch, validation RMSE, filter settings, and how it was made."""
    from estimators.ekf import config_changes, config_of
    from lfgnss.datasets import split_parts

    from .provenance import describe

    meta = model.metadata
    config_file = (meta.get("config_file") or {}).get("path")
    name = bundled_name(model.path)
    show_config = f"python -m learning.export --show {shlex.quote(name or str(model.path))} --config prints it"
    if not isinstance(meta.get("config"), dict):
        configuration = f"configuration file: {config_file or 'not recorded'} (the configuration is not stored)"
    elif config_file:
        configuration = (f"configuration file: {config_file} (the configuration as trained, --set included, is "
                         f"stored in the model: {show_config})")
    else:
        configuration = ("configuration file: its path was not recorded, but the configuration itself is stored in "
                         f"the model: {show_config}")
    members = ensemble_members(meta)
    if members:                                         # each network's own training run
        made = [line for i, m in enumerate(members)
                for line in [f"network {i}:", *(f"  {x}" for x in describe(m.get("provenance")))]]
    elif meta.get("provenance"):
        made = describe(meta["provenance"])
    elif name is not None:
        made = [f"provenance: not recorded (trained before lfgnss recorded the command and git commit); the command "
                f"that made it is in the {MODEL_PREFIX}{name}.npz row of {BUNDLED_README}"]
    else:
        made = ["provenance: not recorded (this file was written before lfgnss recorded how a model was made: the "
                "command, working folder and git commit of its training run)"]
    untrained = untrained_reason(model)
    val = meta.get("val_rmse_3d_m")
    versions = meta.get("versions") or {}
    data = (meta.get("config") or {}).get("data", {})
    seen = set(split_parts(data.get("val_split", "val"))) & set(split_parts(data.get("train_split", "train")))
    where = (" (on trained epochs)" if seen and val is not None else "") + \
        (" (in the training filter)" if meta.get("refilter") and val is not None else "") + \
        (" (RTS-smoothed positions: use it with --smooth)" if trained_smoothed(meta) and val is not None else "")
    return [f"{model.path}",
            f"trained on: {trained_on(meta)}; epoch {meta.get('epoch')}, validation 3D RMSE "
            f"{'-' if val is None else f'{val:.3f} m'}{where}" + (" (its first network)" if meta.get("ensemble")
                                                                  else ""),
            *ensemble_lines(meta),
            f"features: {', '.join(model.feature_names)}" + (f" ({', '.join(model.normaliser.signed_log)} as "
                                                               "sign(x) ln(1 + |x|))" if model.normaliser.signed_log
                                                               else ""),
            *([] if trained_systems(meta) is None else [f"constellations trained on: {trained_systems(meta)}"]),
            f"filter (settings other than the defaults): {config_changes(config_of(model))}",
            *([] if untrained is None else [f"warning: {untrained}"]),
            *refilter_lines(meta),
            configuration,
            *made,
            f"{'network exported' if meta.get('refilter') else 'written'} {meta.get('created_utc', '?')} by lfgnss "
            f"{versions.get('lfgnss', '?')}, torch {versions.get('torch', '?')}"]


def ensemble_lines(metadata: dict) -> list[str]:
    """``--show`` lines on an ensemble file's networks (none for a single network)."""
    ensemble = metadata.get("ensemble")
    if not ensemble:
        return []

    def member(m: dict) -> str:
        val = m.get("val_rmse_3d_m")
        return (f"seed {m.get('seed')}, epoch {m.get('epoch')}, validation 3D RMSE "
                f"{'-' if not isinstance(val, (int, float)) else f'{val:.3f} m'} "
                f"({m.get('checkpoint') or 'checkpoint not recorded'}"
                + (f", via {m['model_file']})" if m.get("model_file") else ")"))

    def grown(records: list, depth: int = 1) -> list[str]:
        lines = []
        for g in records or []:
            done = g.get("exported") or {}
            lines += [f"{'  ' * depth}grown from {g.get('model_file')} (sha256 {g.get('sha256_16')}..., "
                      f"{g.get('networks')} networks, put together {done.get('created_utc', '?')}: "
                      f"{done.get('command') or 'command not recorded'})", *grown(g.get("grown_from"), depth + 1)]
        return lines

    from .provenance import code_text

    members, exported = ensemble_members(metadata), ensemble.get("exported") or {}
    return [f"ensemble of {len(members)} networks of one recipe ({ensemble.get('combine')}):",
            *(f"  {i}: {member(m)}" for i, m in enumerate(members)),
            f"  put together {exported.get('created_utc', '?')} in {exported.get('cwd', '?')}, "
            f"{code_text(exported.get('git'))}: {exported.get('command') or '(called from Python, no command line)'}",
            *grown(ensemble.get("grown_from"))]


def _ekf_assignment(text: str) -> tuple[str, object]:
    """``"zupt_sigma_m_s=0.02"`` -> ``("zupt_sigma_m_s", 0.02)`` (a TOML value; ``none`` for None)."""
    from .train import _parse_value

    if "=" not in text:
        raise ValueError(f"expects KEY=VALUE, got {text!r}")
    key, value = (part.strip() for part in text.split("=", 1))
    if not key:
        raise ValueError(f"expects KEY=VALUE, got {text!r}")
    if value.lower() in ("none", "null"):
        return key, None
    parsed = _parse_value(value)
    if isinstance(parsed, str) and "_" not in value:
        try:
            parsed = float(value)                   # ".5" and "5." are numbers to a user, not TOML
        except ValueError:
            pass
    return key, parsed


def main(argv: list[str] | None = None) -> int:
    """``python -m learning.export CHECKPOINT OUT.npz`` writes a model file (several CHECKPOINTs, or model files
    and CHECKPOINTs: an ensemble, ``export_ensemble``); ``--show MODEL.npz`` describes one (``--show MODEL.npz
    --config`` prints its stored training configuration).

    Exit status 0; 2 for bad input (one line naming the file).
    """
    import argparse

    from lfgnss.errors import INPUT_ERRORS, input_line, path_option

    from .provenance import command_line

    p = argparse.ArgumentParser(prog="python -m learning.export",
                                description="Write a training checkpoint (best.pt / last.pt of learning.train) as a "
                                            "model file, or describe a model file.", formatter_class=PlainHelp)
    p.add_argument("paths", nargs="*", type=path_option, metavar="PATH",
                   help="CHECKPOINT [CHECKPOINT ...] OUT.npz: best.pt or last.pt of a learning.train run, and the "
                        "model file to write (.npz); several "
                        "checkpoints (runs of one recipe with different seeds, train.seed) are written as one "
                        "ensemble: R the geometric mean of the networks', v^c their mean; a model file among "
                        "them adds its networks (grows an ensemble by the seeds trained since)")
    p.add_argument("--show", metavar="MODEL", type=path_option,
                   help="describe a model file (or a bundled model by name: default, hk-tst-2019, ...): its data, "
                        "filter and how it was made (command, git commit, where recorded)")
    p.add_argument("--config", action="store_true",
                   help="with --show: print the training configuration stored in the model instead, as TOML "
                        "(python -m learning.train --config takes it)")
    p.add_argument("--ekf", action="append", default=[], metavar="KEY=VALUE",
                   help="write the model to run in a filter with this EKF setting changed (estimators.EkfConfig; "
                        "repeatable); the source may then be a model file (.npz), and the change is recorded")
    args = p.parse_intermixed_args(argv)     # OUT may follow --ekf KEY=VALUE
    args.checkpoint, args.out, members = (args.paths[0], args.paths[-1], args.paths[:-1]) if len(args.paths) > 1 \
        else ((args.paths or [None])[0], None, [])
    members = [source_file(m) for m in members]                 # a bundled model's name: its file
    args.checkpoint = members[0] if members else args.checkpoint
    if args.config and args.show is None:
        p.error("--config goes with --show MODEL: it prints the training configuration stored in that model file")
    if (args.show is None) == (args.checkpoint is None) or (args.checkpoint is not None and args.out is None):
        p.error("give CHECKPOINT OUT.npz to export, or --show MODEL.npz to describe a model file")
    if args.show is not None and args.ekf:
        p.error("--ekf changes a filter while writing a model file; --show only describes one")
    if len(members) > 1 and args.ekf:
        p.error("--ekf takes one source: write the ensemble first, then change its filter "
                "(python -m learning.export ENSEMBLE.npz OUT.npz --ekf KEY=VALUE)")
    try:
        if args.show is not None:
            if str(args.show).endswith(".pt"):
                raise InputError(args.show, "a training checkpoint, not a model file: export it first "
                                            f"(python -m learning.export {args.show} model.npz)")
            model = load_model(args.show)
            if args.config:
                print_stdout(config_text(model), end="")
            else:
                print_stdout("\n".join(describe_model(model)))
            return 0
        if not str(args.out).endswith(".npz"):
            raise InputError(args.out, "give the model file a .npz name (numpy would add it)")
        if len(members) == 1 and str(members[0]).endswith(".npz") and not args.ekf:
            raise InputError(members[0], "a model file, not a training checkpoint: give --ekf KEY=VALUE to write it "
                                         "with another filter setting, checkpoints of other seeds to grow it into an "
                                         "ensemble, or --show to describe it")
        changes = {}
        try:
            for key, value in (_ekf_assignment(a) for a in args.ekf):
                if key in changes:
                    raise ValueError(f"{key} given twice")
                changes[key] = value
        except ValueError as exc:
            p.error(f"--ekf: {str(exc).removeprefix('estimators/models.py: ')}")
        if changes:
            try:
                written = refilter_model(args.checkpoint, args.out, changes,
                                         command_line("python -m learning.export", list(argv or sys.argv[1:])))
            except ModelFileError:
                raise
            except (TypeError, ValueError) as exc:      # the filter's own check names its source file: not the user's
                p.error(f"--ekf: {str(exc).removeprefix('estimators/models.py: ')}")
        else:
            written = export_ensemble(members, args.out,
                                      command_line("python -m learning.export", list(argv or sys.argv[1:])))
        model = load_model(written)
        epochs = member_epochs(model.metadata)
        if len(members) > 1:
            print(f"{written}: ensemble of {len(epochs)} networks: {', '.join(map(str, members))} (epochs "
                  f"{', '.join(map(str, epochs))})")
        else:
            what = f"ensemble of {len(epochs)} networks" if len(epochs) > 1 else f"epoch {epochs[0]}"
            print(f"{written}: model of {args.checkpoint} ({what})" + (f", filter changed: {', '.join(args.ekf)}"
                                                                        if changes else ""))
        untrained = untrained_reason(model)
        if untrained is not None:           # as lfgnss.solve warns of it when the file is used
            print(f"warning: {written}: {untrained}", file=sys.stderr)
    except (*INPUT_ERRORS, OSError) as exc:
        p.exit(2, f"{p.prog}: error: {input_line(exc)}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
