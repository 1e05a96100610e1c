"""data.signed_log: heavy-tailed features standardised as sign(x) ln(1 + |x|), in training and in model files."""
import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from learning.data import signed_log_names
from learning.export import ModelFileError, load_model
from learning.normalise import Normaliser
from lfgnss.simulate import simulate_sequence
from tests.tiny_training import TINY, sets


def _heavy_tailed(seed: int = 1):
    """A synthetic sequence whose residual feature is mostly within 0.3 of 0 with a few capped slots at -95 (as the
    DOP contributions of a singular leave-one-out)."""
    seq = simulate_sequence(40, seed=seed)
    f = seq.features.copy()
    rng = np.random.default_rng(seed)
    f[..., 3] = rng.normal(-0.05, 0.1, seq.mask.shape)
    k, slot = np.argwhere(seq.mask)[[5, 50]].T
    f[k, slot, 3] = -95.0
    return replace(seq, features=f)


def test_the_signed_log_keeps_a_few_capped_slots_from_setting_the_spread():
    seq = _heavy_tailed()
    names = ("cn0", "residual")
    plain = Normaliser.fit([seq], names)
    logged = Normaliser.fit([seq], names, ["residual"])
    raw = seq.features[seq.mask][:, [0, 3]]
    g = np.sign(raw[:, 1]) * np.log1p(np.abs(raw[:, 1]))
    assert logged.mean[1] == pytest.approx(g.mean()) and logged.std[1] == pytest.approx(g.std())
    assert logged.mean[0] == plain.mean[0] and logged.std[0] == plain.std[0]        # cn0 as before
    assert plain.std[1] > 5 * logged.std[1]              # two slots of -95 set the plain std, not the logged one
    x = logged.apply(seq.features[..., [0, 3]], seq.mask)
    np.testing.assert_allclose(x[seq.mask][:, 1], (g - logged.mean[1]) / logged.std[1])
    assert not x[~seq.mask].any()
    xt = logged.apply_torch(torch.as_tensor(seq.features[..., [0, 3]]), torch.as_tensor(seq.mask))
    np.testing.assert_allclose(xt.numpy(), x, rtol=1e-12)


def test_the_option_is_recorded_and_a_record_without_it_is_plain():
    seq = _heavy_tailed()
    logged = Normaliser.fit([seq], ("cn0", "residual"), ["residual"])
    again = Normaliser.from_dict(json.loads(json.dumps(logged.to_dict())))
    assert again.signed_log == ("residual",) and again.same_as(logged)
    plain = logged.to_dict()
    del plain["signed_log"]                             # a model file from before the option
    assert Normaliser.from_dict(plain).signed_log == () and not Normaliser.from_dict(plain).same_as(logged)
    assert "signed_log" not in Normaliser.fit([seq], ("cn0",)).to_dict()      # plain files stay as they were
    with pytest.raises(ValueError, match=r"signed_log names \['dpc_gdop'\], which are not among the features"):
        Normaliser.fit([seq], ("cn0", "residual"), ["dpc_gdop"])


def test_configuration_names():
    dpc = ("dpc_gdop", "dpc_pdop", "dpc_hdop", "dpc_vdop")
    assert signed_log_names(["dpc"], ("cn0", "elevation", *dpc)) == dpc
    assert signed_log_names(["dpc", "dpc_gdop"], ("cn0", *dpc)) == dpc
    assert signed_log_names(["dpc"], ("cn0", "elevation")) == ()         # the w/o DPC ablation of a logged recipe
    with pytest.raises(ValueError, match=r"'dpc_gdp' is not a feature of the model .*did you mean 'dpc_gdop'"):
        signed_log_names(["dpc_gdp"], ("cn0", *dpc))
    with pytest.raises(ValueError, match="'cn0' must stay in its own units with model.r_prior = 'heuristic'"):
        signed_log_names(["cn0"], ("cn0", "elevation"), "heuristic")
    assert signed_log_names(["cn0"], ("cn0", "elevation")) == ("cn0",)


def test_a_bad_setting_is_one_line_on_the_command_line(capsys):
    from learning.train import main

    with pytest.raises(SystemExit) as exit_info:
        main(["--config", "synthetic", *sets(["data.signed_log=['resdual']"]), "--out", "unused"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "data.signed_log: 'resdual' is not a feature" in err


def test_a_trained_model_file_applies_the_signed_log_it_was_trained_with(tmp_path):
    from learning.train import adopt_init, load_config, train

    config = load_config("synthetic", [*TINY, "data.signed_log=['residual']"])
    train(config, tmp_path / "run", progress=False)
    model = load_model(tmp_path / "run" / "model.npz")
    assert model.normaliser.signed_log == ("residual",)
    from learning.export import describe_model
    assert "features: cn0, elevation, azimuth, residual, dpc_gdop, dpc_pdop, dpc_hdop, dpc_vdop (residual as sign(x) " \
        "ln(1 + |x|))" in describe_model(model)
    seq = _heavy_tailed(3)
    features = seq.features[..., list(map(seq.feature_names.index, model.feature_names))]
    r, vc = model.predict(features, seq.mask)
    # the same network fed the logged feature through a plain normaliser of the same statistics
    logged = model.normaliser.transform(features)
    model.normaliser = replace(model.normaliser, signed_log=())
    r0, vc0 = model.predict(logged, seq.mask)
    np.testing.assert_allclose(r, r0, rtol=1e-6)
    np.testing.assert_allclose(vc, vc0, rtol=1e-6, atol=1e-9)
    r1, _ = model.predict(features, seq.mask)                   # without the logarithm: other noise
    assert not np.allclose(r1[seq.mask], r[seq.mask])
    tuned = load_config("synthetic", [*TINY, f"train.init={tmp_path / 'run' / 'model.npz'}"])
    assert adopt_init(tuned)["data"]["signed_log"] == ["residual"]


def test_a_model_file_with_a_bad_signed_log_is_refused(tmp_path):
    from learning.train import load_config, train

    train(load_config("synthetic", [*TINY, "data.signed_log=['residual']"]), tmp_path / "run", progress=False)
    src = tmp_path / "run" / "model.npz"
    for value, why in (("residual", "normaliser.signed_log must be a list of feature names"),
                       (["dpc_gdp"], r"signed_log names \['dpc_gdp'\], which are not among the features")):
        with np.load(src) as z:
            arrays = dict(z)
        meta = json.loads(str(arrays["metadata"]))
        meta["normaliser"]["signed_log"] = value
        arrays["metadata"] = np.array(json.dumps(meta))
        bad = tmp_path / "bad.npz"
        np.savez(bad, **arrays)
        with pytest.raises(ModelFileError, match=why):
            load_model(bad)


def test_review_crossval_reuse_elsewhere_refits_with_the_signed_log(tmp_path, monkeypatch):
    """Review: a --reuse rescore on another machine refitted the fold's normaliser without the signed log, so every
    signed-log fold model was refused as 'normalised otherwise'."""
    import learning.crossval as cv
    import learning.train as tr

    config = tr.load_config("synthetic", [*TINY, "data.signed_log=['residual']"])
    cv.crossval(config, 2, tmp_path / "cv", progress=False, only=[0])
    saved = tr.read_checkpoint(tmp_path / "cv" / "fold0" / "last.pt")
    parts = {ds: cv.fold_sequences(s, 2, 0) for ds, s in cv.cv_sequences(config).items()}
    held = [s for _, h in parts.values() for s in h]
    trained = [s for t, _ in parts.values() for s in t]
    monkeypatch.setattr(tr, "source_file_hashes", lambda ds: {"f": "h"})      # synthetic data has no files
    saved["source_files"] = {ds: {"f": "h"} for ds in config["data"]["datasets"]}
    assert cv._same_data_elsewhere(saved, config, held, trained) is None


def test_review_ensembles_and_fine_tuning_name_the_signed_log(tmp_path, capsys):
    """Review: an ensemble of a signed-log and a plain network was refused for 'the feature means or stds'; a
    fine-tuning run given another data.signed_log dropped it without a word."""
    from learning.export import export_ensemble
    from learning.train import load_config, train

    train(load_config("synthetic", [*TINY, "data.signed_log=['residual']"]), tmp_path / "a", progress=False)
    train(load_config("synthetic", [*TINY, "seed=1"]), tmp_path / "b", progress=False)
    with pytest.raises(ModelFileError, match=r"the normaliser's signed_log differs .*\(here: none; there: residual\)"):
        export_ensemble([tmp_path / "a" / "last.pt", tmp_path / "b" / "last.pt"], tmp_path / "ab.npz")
    capsys.readouterr()
    train(load_config("synthetic", [*TINY, f"train.init={tmp_path / 'b' / 'model.npz'}",
                                    "data.signed_log=['residual']"]), tmp_path / "tuned", progress=False)
    assert "data.signed_log of the configuration are replaced" in capsys.readouterr().err
    assert load_model(tmp_path / "tuned" / "model.npz").normaliser.signed_log == ()


def test_review_a_model_file_whose_prior_feature_is_logged_is_refused(tmp_path):
    from learning.train import load_config, train

    train(load_config("synthetic", [*TINY, "model.r_prior='heuristic'"]), tmp_path / "run", progress=False)
    with np.load(tmp_path / "run" / "model.npz") as z:
        arrays = dict(z)
    meta = json.loads(str(arrays["metadata"]))
    meta["normaliser"]["signed_log"] = ["elevation"]
    arrays["metadata"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ModelFileError, match=r"signed_log names \['elevation'\], which the R prior .* own units"):
        load_model(tmp_path / "bad.npz")
