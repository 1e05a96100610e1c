"""Bad model files (fuzzing finds): one-line ModelFileError naming the file and the offending key, never a crash."""
from __future__ import annotations

import glob
import json

import numpy as np
import pytest

from learning.export import ModelFileError, load_model
from lfgnss.errors import InputError
from lfgnss.solve import DEFAULT_MODEL, main


def _rewrite(dst, change_meta=None, change_arrays=None):
    """A copy of the bundled model with its metadata JSON and/or arrays changed."""
    with np.load(DEFAULT_MODEL, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["metadata"]))
    if change_meta:   # changes it in place, or returns the metadata to write instead
        meta = change_meta(meta) or meta
    if change_arrays:
        change_arrays(arrays)
    arrays["metadata"] = np.array(json.dumps(meta))
    np.savez(dst, **arrays)


def _model(**kw):
    return lambda meta: meta["model"].update(kw)


def _prior(**kw):
    return lambda meta: meta["model"]["r_prior"].update(kw)


def _ekf(**kw):
    return lambda meta: meta["ekf_config"].update(kw)


def _delete(*keys):
    def change(meta):
        for key in keys[:-1]:
            meta = meta[key]
        del meta[keys[-1]]
    return change


def _random_bytes(dst):
    dst.write_bytes(np.random.default_rng(0).bytes(5000))


def _npy(dst):
    with open(dst, "wb") as fh:
        np.save(fh, np.zeros(3))


def _pickled(dst):
    np.savez(dst, metadata=np.array([{"format": "x"}], dtype=object))


BAD_META = [   # (id, change of the metadata, text the message must contain besides the file name)
    ("parameters-list", lambda m: m.update(parameters=list(m["parameters"])), "parameters must be a table"),
    ("parameter-shape-text", lambda m: m["parameters"].update({"head.bias": "2"}), "parameters.head.bias"),
    ("metadata-list", lambda m: [m], "metadata"),
    ("model-list", lambda m: m.update(model=[1, 2]), "metadata model must be a table"),
    ("normaliser-text", lambda m: m.update(normaliser="z"), "normaliser"),
    ("ekf-config-string", lambda m: m.update(ekf_config="fast"), "ekf_config"),
    ("ekf-config-text-value", _ekf(gate_sigma="x"), "ekf_config.gate_sigma"),
    ("ekf-config-negative", _ekf(p0_pos_m2=-1.0), "ekf_config: EkfConfig.p0_pos_m2 must be > 0"),
    ("cn0-index-99", _prior(cn0_index=99), "model.r_prior.cn0_index"),
    ("el-index-text", _prior(el_index="1"), "model.r_prior.el_index"),
    ("prior-std-nan", _prior(cn0_std=float("nan")), "model.r_prior.cn0_std"),
    ("prior-missing-key", _delete("model", "r_prior", "floor_m"), "model.r_prior.floor_m"),
    ("r-prior-list", _model(r_prior=[1]), "model.r_prior"),
    ("n-heads-7", _model(n_heads=7), "model.n_heads"),
    ("n-heads-0", _model(n_heads=0), "model.n_heads"),
    ("d-model-text", _model(d_model="64"), "model.d_model"),
    ("hidden-missing", _delete("model", "hidden"), "model.hidden"),
    ("hidden-not-ints", _model(hidden=[64, "x", 64]), "model.hidden"),
    ("hidden-mismatch", _model(hidden=[64, 32, 64]), "model.hidden"),
    ("hidden-too-many", _model(hidden=[64, 128, 64, 8]), "model.hidden"),
    ("layer-norm-eps-text", lambda m: m.update(layer_norm_eps="x"), "layer_norm_eps"),
    ("layer-norm-eps-zero", lambda m: m.update(layer_norm_eps=0), "layer_norm_eps"),
    ("r-floor-negative", _model(r_floor_m2=-5), "model.r_floor_m2"),
    ("r-floor-inf", _model(r_floor_m2=float("inf")), "model.r_floor_m2"),
    ("r-scale-zero", _model(r_scale_m2=0), "model.r_scale_m2"),
    ("r-scale-huge-int", _model(r_scale_m2=10 ** 400), "model.r_scale_m2"),
    ("innovation-text", _model(innovation="no"), "model.innovation"),
]


@pytest.mark.parametrize("change, key", [c[1:] for c in BAD_META], ids=[c[0] for c in BAD_META])
def test_bad_metadata_is_one_line_naming_file_and_key(tmp_path, change, key):
    dst = tmp_path / "bad.npz"
    _rewrite(dst, change_meta=change)
    with pytest.raises(ModelFileError) as info:
        load_model(dst)
    message = str(info.value)
    assert message.startswith(f"{dst}: ") and key in message and "\n" not in message, message
    assert isinstance(info.value, InputError)


def _zero_noise(arrays):
    arrays["param/head.bias"] = np.array([-3e38, 0.0], np.float32)   # softplus(o_R) = 0


def _text_param(arrays):
    arrays["param/head.bias"] = np.array(["a", "b"])


def _drop_bias(arrays):
    del arrays["param/mlp.2.bias"]


BAD_ARRAYS = [   # (id, change of the arrays, change of the metadata, text the message must contain)
    # a floor of 0 is refused (training's least is 1e-6 m^2; the file check accepted 0), so R = 0 cannot reach the EKF
    ("zero-floor", _zero_noise, _model(r_floor_m2=0.0), "metadata model.r_floor_m2 must be a finite number >= 1e-06"),
    ("text-parameter", _text_param, None, "'head.bias'"),
    ("missing-bias", _drop_bias, _delete("parameters", "mlp.2.bias"), "mlp.2.bias"),
    ("text-normaliser", lambda a: a.update(normaliser_mean=np.array(["x"] * 8)), None, "normaliser_mean"),
]


@pytest.mark.parametrize("change, change_meta, key", [c[1:] for c in BAD_ARRAYS], ids=[c[0] for c in BAD_ARRAYS])
def test_bad_arrays_are_one_line_naming_file_and_key(tmp_path, change, change_meta, key):
    dst = tmp_path / "bad.npz"
    _rewrite(dst, change_meta=change_meta, change_arrays=change)
    with pytest.raises(ModelFileError) as info:
        load_model(dst)
    message = str(info.value)
    assert message.startswith(f"{dst}: ") and key in message and "\n" not in message, message


@pytest.mark.parametrize("write, text", [(_random_bytes, "not an lfgnss model file"),
                                         (_npy, "not an lfgnss model file"),
                                         (_pickled, "not an lfgnss model file"),
                                         (lambda p: p.write_bytes(b""), "empty file"),
                                         (lambda p: __import__("torch").save({"epoch": 1}, p),
                                          "a training checkpoint, not a model file: export it first (python -m "
                                          "learning.export")],
                         ids=["random-bytes", "npy", "pickled", "empty", "checkpoint"])
def test_not_a_model_file_says_so(tmp_path, write, text):
    dst = tmp_path / "junk.npz"
    write(dst)
    with pytest.raises(ModelFileError) as info:
        load_model(dst)
    message = str(info.value)
    assert message.startswith(f"{dst}: ") and text in message and "allow_pickle" not in message, message
    assert "\n" not in message


def test_bundled_models_still_load():
    paths = glob.glob(str(DEFAULT_MODEL.parent / "*.npz"))
    assert paths and all(load_model(p).feature_names for p in paths)


@pytest.mark.parametrize("change", [_model(n_heads=7), _prior(cn0_index=99)], ids=["n-heads-7", "cn0-index-99"])
def test_cli_bad_model_is_exit_2_one_line(tmp_path, capsys, change):
    bad = tmp_path / "BAD.npz"
    _rewrite(bad, change_meta=change)
    assert main(["--model", str(bad), "--out", str(tmp_path / "out"), "--quiet", "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(bad) in err, err
    assert "internal error" not in err and "Traceback" not in err


def test_forward_pass_failure_is_a_model_file_error(monkeypatch):
    """Backstop: whatever the checks miss and breaks the test forward pass is the file's fault, in one line."""
    from learning.export import LfgnssModel

    def broken(self, x, m):
        raise IndexError("index 99 is out of bounds\nfor axis 2")

    monkeypatch.setattr(LfgnssModel, "_forward", broken)
    with pytest.raises(ModelFileError) as info:
        load_model(DEFAULT_MODEL)
    message = str(info.value)
    assert message.startswith(f"{DEFAULT_MODEL}: the network does not run (IndexError: index 99") and "\n" not in message
