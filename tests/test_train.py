"""End-to-end training on simulated sequences: learning, resume, reproducibility, gradients."""
import copy
import csv
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from learning.export import load_model
from learning.train import (_files_absolute, _index_batch, build_model, ekf_config, evaluate, jitter_features, load_config,
                            load_sequences, main, prepare, run_filter, train)
from learning.loss import make_loss
from lfgnss.paths import model_path

EPOCHS = 4
SETTINGS = ["data.datasets=['synthetic']", "data.synthetic.n_epochs=150", "data.synthetic.nlos_fraction=0.4",
            "data.synthetic.train_seeds=[1, 2]", "data.synthetic.val_seeds=[101]", "data.window=20",
            "data.stride=10", "train.batch_size=4", "train.lr=1e-2", f"train.epochs={EPOCHS}", "threads=1"]


@pytest.fixture(scope="module")
def config():
    return load_config("learning/configs/default.toml", SETTINGS)


@pytest.fixture(scope="module")
def prepared(config):
    return prepare(config)


@pytest.fixture(scope="module")
def full_run(config, prepared, tmp_path_factory):
    out = tmp_path_factory.mktemp("full")
    return out, train(config, out, progress=False, prepared=prepared)


def test_validation_error_drops(full_run):
    out, history = full_run
    assert [h["epoch"] for h in history] == list(range(EPOCHS + 1))
    # the selected (best-validation) model at least halves the untrained model's error
    assert min(h["val_rmse_3d_m"] for h in history[1:]) < 0.5 * history[0]["val_rmse_3d_m"]
    for name in ("last.pt", "best.pt", "log.csv", "curves.png", "model.npz"):
        assert (out / name).exists(), name
    with open(out / "log.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == EPOCHS + 1 and set(rows[0]) >= {"epoch", "train_loss", "val_rmse_3d_m", "seconds"}
    assert rows[0]["train_loss"] == "" and all(np.isfinite(float(r["train_loss"])) for r in rows[1:])   # no step yet
    model = load_model(out / "model.npz")
    assert model.metadata["data_fingerprints"][0]["dataset"] == "synthetic"
    spans = model.metadata["data_spans"]          # where each train and val piece lies, for the benchmark's check
    assert [(s["split"], s["sequence"]) for s in spans] == [(p["split"], p["sequence"])
                                                            for p in model.metadata["data_fingerprints"]]
    assert all(s["gps_s"][0] < s["gps_s"][1] and len(s["place_ecef_m"]) == 3 for s in spans)


def test_resume_equals_uninterrupted_run_via_cli(full_run, tmp_path):
    out, history = full_run
    half = [s for s in SETTINGS if not s.startswith("train.epochs")] + ["train.epochs=2"]
    args = ["--config", "learning/configs/default.toml", "--out", str(tmp_path), "--no-progress"]
    assert main(args + [x for s in half for x in ("--set", s)]) == 0
    assert main(args + ["--resume", "--set", f"train.epochs={EPOCHS}"]) == 0
    resumed = torch.load(tmp_path / "last.pt", weights_only=False)
    straight = torch.load(out / "last.pt", weights_only=False)
    for a, b in zip(resumed["history"], straight["history"]):
        assert a["train_loss"] == b["train_loss"] or (np.isnan(a["train_loss"]) and np.isnan(b["train_loss"]))
        assert a["val_rmse_3d_m"] == b["val_rmse_3d_m"]
    for key, value in straight["model"].items():
        assert torch.equal(resumed["model"][key], value), key


def test_same_seed_same_final_loss(config, prepared, full_run, tmp_path):
    again = train(config, tmp_path, progress=False, prepared=prepared, export=False)
    assert again[-1]["train_loss"] == full_run[1][-1]["train_loss"]
    assert again[-1]["val_rmse_3d_m"] == full_run[1][-1]["val_rmse_3d_m"]


def test_gradient_reaches_network_through_filter(config, prepared):
    torch.manual_seed(0)
    model = build_model(config, len(prepared.feature_names))
    batch = _index_batch(prepared.train_batch, np.arange(4))
    pos = run_filter(model, batch, n_systems=prepared.n_systems, ekf_cfg=ekf_config(config))
    make_loss("hem")(pos, batch.truth_ecef_m).backward()
    g = model.embed.weight.grad
    assert g is not None and torch.isfinite(g).all() and g.abs().sum() > 0


def test_test_split_is_refused(config, tmp_path):
    with pytest.raises(ValueError, match="test split"):
        load_sequences("synthetic", "test", config)
    bad = load_config(None, SETTINGS + ["data.val_split='test'"])
    with pytest.raises(ValueError, match="test split"):
        train(bad, tmp_path, progress=False)


def test_existing_run_needs_resume(full_run, config):
    with pytest.raises(ValueError, match="--resume"):
        train(config, full_run[0], progress=False)


def test_feature_selection_normaliser_and_padding():
    from learning.data import DPC_FEATURES, Window, collate, resolve_feature_names
    from learning.normalise import Normaliser
    from lfgnss.simulate import simulate_sequence

    assert resolve_feature_names(None, ["dpc"]) == ("cn0", "elevation", "azimuth", "residual")
    assert load_config("learning/configs/no_dpc_no_hem.toml")["loss"]["kind"] == "rmse"
    a = simulate_sequence(30, seed=1)                   # 14 slots
    b = simulate_sequence(30, seed=2, n_slots=20)       # 20 slots, 6 padded
    names = resolve_feature_names(None, ["dpc"])
    norm = Normaliser.fit([a, b], names)
    valid = np.concatenate([a.features[a.mask][:, :4], b.features[b.mask][:, :4]])
    np.testing.assert_allclose(norm.mean, valid.mean(axis=0))
    batch = collate([a, b], [Window(0, 0, 10), Window(1, 5, 10)], norm)
    assert batch.features.shape == (2, 10, 20, 4) and batch.features.dtype == torch.float32
    assert not batch.mask[0, :, 14:].any() and (batch.features[~batch.mask] == 0).all()
    np.testing.assert_array_equal(batch.cn0_dbhz[1].numpy(), b.cn0_dbhz[5:15])      # raw C/N0, for the Doppler law
    np.testing.assert_array_equal(batch.cn0_dbhz[0, :, :14].numpy(), a.cn0_dbhz[:10])
    x = norm.apply_torch(torch.as_tensor(b.features[..., :4]), torch.as_tensor(b.mask))
    np.testing.assert_allclose(x.numpy(), norm.apply(b.features[..., :4], b.mask))
    assert not set(DPC_FEATURES) & set(norm.feature_names)


def test_normaliser_refuses_non_finite_features_and_keeps_a_small_spread():
    """Review: a NaN feature dropped its whole slot from the statistics and trained on (an all-NaN column said 'no
    valid satellite slot'); the exported model then refused the sequence it was trained on. The one-pass variance
    lost a spread of 1e-3 about a mean of 1e5."""
    from dataclasses import replace

    from learning.normalise import Normaliser
    from lfgnss.simulate import simulate_sequence

    seq = simulate_sequence(30, seed=1)
    bad = seq.features.copy()
    k, slot = np.argwhere(seq.mask)[3]
    bad[k, slot, 0] = np.nan
    with pytest.raises(ValueError, match=rf"feature 'cn0' of sequence {seq.name!r} is not finite at 1 valid "
                                         rf"satellite slot\(s\) \(first: epoch {k}, slot {slot}\)"):
        Normaliser.fit([replace(seq, features=bad)], ("cn0", "elevation"))
    padded = seq.features.copy()
    padded[~seq.mask] = np.nan                                  # padded slots may hold anything
    assert Normaliser.fit([replace(seq, features=padded)], ("cn0",)).same_as(Normaliser.fit([seq], ("cn0",)))
    big = seq.features.copy()
    big[..., 0] = 1e5 + 1e-3 * np.random.default_rng(0).standard_normal(seq.mask.shape)
    std = Normaliser.fit([replace(seq, features=big)], ("cn0",)).std[0]
    assert std == pytest.approx(big[..., 0][seq.mask].std(), rel=1e-6)


def test_a_labelled_piece_shorter_than_the_window_is_named(config, capsys):
    """A training piece with labels but fewer epochs than a window cannot be trained on: a note names it."""
    from lfgnss.simulate import simulate_sequence

    pieces = {"train": [simulate_sequence(60, seed=1), simulate_sequence(12, seed=2)],
              "val": [simulate_sequence(30, seed=3)]}
    prep = prepare(config, source=lambda ds, split, cfg: pieces[split])
    assert {w.seq_index for w in prep.windows} == {0}
    err = capsys.readouterr().err
    assert "1 training piece(s) shorter than the 20-epoch window" in err and "(12 labelled epochs)" in err
    prepare(config, source=lambda ds, split, cfg: pieces[split][:1] if split == "train" else pieces[split])
    assert "shorter than" not in capsys.readouterr().err


def test_weight_decay_r_only_and_last_epoch_settings(config, prepared, tmp_path):
    """train.weight_decay switches to AdamW; model.compensation = false trains R only; train.select = "last"
    exports the last epoch whatever validation says; bad settings and a changed decay on resume are refused."""
    import copy

    cfg = copy.deepcopy(config)
    cfg["train"]["epochs"] = 2
    cfg["train"]["weight_decay"] = 0.5
    cfg["train"]["select"] = "last"
    cfg["train"]["lr"] = 0.3                     # too large: validation is best at epoch 0, last is epoch 2
    cfg["model"]["compensation"] = False
    history = train(cfg, tmp_path, progress=False, prepared=prepared, export=True)
    assert np.isfinite(history[-1]["train_loss"])
    group = torch.load(tmp_path / "last.pt", weights_only=False)["optimiser"]["param_groups"][0]
    assert group["weight_decay"] == 0.5 and group["decoupled_weight_decay"] is True      # AdamW, not Adam's L2
    assert torch.load(tmp_path / "best.pt", weights_only=False)["epoch"] == 0
    model = load_model(tmp_path / "model.npz")
    assert model.metadata["epoch"] == 2 and model.metadata["val_rmse_3d_m"] == history[-1]["val_rmse_3d_m"]
    _, vc = model(load_sequences("synthetic", "val", cfg)[0])
    assert np.all(vc == 0.0)
    cfg["train"]["select"] = "best"
    with pytest.raises(ValueError, match="train.select"):
        train(cfg, tmp_path / "bad", progress=False, prepared=prepared)
    with pytest.raises(ValueError, match="model.compensation"):
        load_config("learning/configs/default.toml", ["model.compensation='False'"])
    with pytest.raises(ValueError, match="weight_decay cannot change"):
        train(cfg, tmp_path, resume=True, overrides=["train.weight_decay=0.0"], progress=False, prepared=prepared)


def test_weight_decay_alone_changes_the_run(config, prepared, full_run, tmp_path):
    import copy

    cfg = copy.deepcopy(config)
    cfg["train"]["epochs"] = 1
    cfg["train"]["weight_decay"] = 0.5
    history = train(cfg, tmp_path, progress=False, prepared=prepared, export=False)
    assert history[0]["val_rmse_3d_m"] == full_run[1][0]["val_rmse_3d_m"]   # same start (seed) ...
    assert history[1]["train_loss"] != full_run[1][1]["train_loss"]         # ... and only the decay differs
    assert history[1]["val_rmse_3d_m"] != full_run[1][1]["val_rmse_3d_m"]


def test_feature_noise_jitters_only_the_training_features_of_real_satellites(config, prepared, full_run, tmp_path):
    """train.feature_noise: N(0, std^2) on the normalised features of masked-in slots, reproducible per seed and
    epoch; the first validation (epoch 0) is the run's without it; a negative std is refused."""
    import copy

    batch = _index_batch(prepared.train_batch, np.arange(3))
    assert jitter_features(batch, 0.0, torch.Generator().manual_seed(1)) is batch
    a = jitter_features(batch, 0.5, torch.Generator().manual_seed(1))
    b = jitter_features(batch, 0.5, torch.Generator().manual_seed(1))
    assert torch.equal(a.features, b.features) and torch.equal(a.pr_m, batch.pr_m)
    delta = (a.features - batch.features)
    assert torch.all(delta[~batch.mask] == 0)                               # padding stays inert
    assert float(delta[batch.mask].std()) == pytest.approx(0.5, rel=0.05)
    cfg = copy.deepcopy(config)
    cfg["train"]["epochs"] = 1
    cfg["train"]["feature_noise"] = 0.3
    history = train(cfg, tmp_path, progress=False, prepared=prepared, export=False)
    assert history[0]["val_rmse_3d_m"] == full_run[1][0]["val_rmse_3d_m"]
    assert history[1]["train_loss"] != full_run[1][1]["train_loss"]
    model = build_model(cfg, len(prepared.feature_names), prepared.normaliser)      # validation is noise-free:
    model.load_state_dict(torch.load(tmp_path / "last.pt", weights_only=False)["model"])   # the saved weights
    again = evaluate(model, prepared.val_batches, n_systems=prepared.n_systems, ekf_cfg=ekf_config(cfg))[0]
    assert again == pytest.approx(history[1]["val_rmse_3d_m"], rel=1e-9)              # give the logged figure
    with pytest.raises(ValueError, match="train.feature_noise"):
        load_config("learning/configs/default.toml", ["train.feature_noise=-0.1"])


def test_weight_averaging_is_an_ema_of_epoch_weights_and_resumes(config, prepared, full_run, tmp_path):
    """train.ema_decay = d: the validated and saved weights are avg_k = d avg_(k-1) + (1 - d) w_k over the
    end-of-epoch weights w_k (avg_1 = w_1); training itself is unchanged; --resume continues the average
    exactly; bad values and a changed decay on resume are refused."""
    import copy

    cfg = copy.deepcopy(config)
    cfg["train"]["ema_decay"] = 0.5
    cfg["train"]["epochs"] = 3
    straight = train(cfg, tmp_path / "straight", progress=False, prepared=prepared, export=True)
    # the raw weights follow the run without averaging; only the validated weights differ
    assert [h["train_loss"] for h in straight[1:]] == [h["train_loss"] for h in full_run[1][1:4]]
    assert straight[0]["val_rmse_3d_m"] == full_run[1][0]["val_rmse_3d_m"]
    assert straight[1]["val_rmse_3d_m"] == full_run[1][1]["val_rmse_3d_m"]     # avg_1 = w_1, validated
    assert straight[2]["val_rmse_3d_m"] != full_run[1][2]["val_rmse_3d_m"]

    raw, avg = [], None
    for epochs in (1, 2, 3):                    # one epoch at a time, resuming: w_k from each checkpoint
        cfg["train"]["epochs"] = epochs
        train(cfg, tmp_path / "steps", resume=epochs > 1, overrides=[f"train.epochs={epochs}"], progress=False,
              prepared=prepared, export=False)
        ckpt = torch.load(tmp_path / "steps" / "last.pt", weights_only=False)
        raw.append(ckpt["trained_model"])
        avg = ckpt["model"]
    expected = dict(raw[0])
    for w in raw[1:]:
        expected = {k: 0.5 * expected[k] + 0.5 * w[k] for k in expected}
    done = torch.load(tmp_path / "straight" / "last.pt", weights_only=False)
    for key, value in expected.items():
        torch.testing.assert_close(avg[key], value, rtol=1e-6, atol=1e-7)
        assert torch.equal(done["model"][key], avg[key]), key          # resumed == uninterrupted
    exported = load_model(tmp_path / "straight" / "model.npz")
    assert exported.metadata["config"]["train"]["ema_decay"] == 0.5
    best = torch.load(tmp_path / "straight" / "best.pt", weights_only=False)["model"]
    for key, value in best.items():                                     # the averaged weights are exported
        np.testing.assert_array_equal(exported.params[key], value.numpy().astype(np.float32))

    for bad in ("1.0", "-0.1", "true", "'0.9'"):
        with pytest.raises(ValueError, match="train.ema_decay"):
            load_config("learning/configs/default.toml", [f"train.ema_decay={bad}"])
    with pytest.raises(ValueError, match="ema_decay cannot change"):
        train(cfg, tmp_path / "steps", resume=True, overrides=["train.ema_decay=0.9"], progress=False,
              prepared=prepared)


def test_fine_tuning_starts_from_a_model_file(config, full_run, tmp_path, capsys):
    """train.init = a model file: epoch 0 is that model (same weights, same normalisation, so the same
    validation error), its network and features replace the configuration's, training moves on from it, and
    the new file records what it started from; a missing file is one clear error."""
    import copy
    import hashlib

    from lfgnss.benchmark import _trained_on
    from learning.crossval import crossval
    from learning.export import ModelFileError

    out, _ = full_run
    start = load_model(out / "model.npz")
    cfg = copy.deepcopy(config)
    cfg["train"].update(init=str(out / "model.npz"), epochs=1, lr=1e-3)
    cfg["model"]["d_model"] = 32                                # replaced by the init model's network
    cfg["data"]["drop_features"] = ["dpc"]                      # and its features
    history = train(cfg, tmp_path / "tuned", progress=False)
    assert "network and features are those of" in capsys.readouterr().err
    assert history[0]["val_rmse_3d_m"] == pytest.approx(start.metadata["val_rmse_3d_m"], rel=1e-9, abs=0)
    assert history[1]["val_rmse_3d_m"] != history[0]["val_rmse_3d_m"]
    tuned = load_model(tmp_path / "tuned" / "model.npz")
    assert tuned.metadata["model"] == start.metadata["model"] and tuned.feature_names == start.feature_names
    np.testing.assert_array_equal(tuned.normaliser.mean, start.normaliser.mean)
    record = tuned.metadata["init_model"]
    assert record["sha256_16"] == hashlib.sha256((out / "model.npz").read_bytes()).hexdigest()[:16]
    assert record["datasets"] == ["synthetic"] and record["data_fingerprints"] == start.metadata["data_fingerprints"]
    assert record["data_spans"] == start.metadata["data_spans"] and record["source_files"] == {"synthetic": {}}
    assert record["epoch"] == start.metadata["epoch"] and record["init_model"] is None
    assert record["select"] == start.metadata["config"]["train"]["select"]
    assert _trained_on(tuned) == "synthetic (train), fine-tuned from synthetic (train)"
    assert load_model(out / "model.npz").metadata["init_model"] is None

    cfg["train"]["epochs"] = 2                                  # the fine-tuned run resumes like any other
    train(cfg, tmp_path / "tuned", resume=True, overrides=["train.epochs=2"], progress=False)
    assert load_model(tmp_path / "tuned" / "model.npz").metadata["init_model"] == record

    cv = copy.deepcopy(cfg)
    cv["train"]["epochs"] = 1
    crossval(cv, 2, tmp_path / "cv", progress=False)            # the init model saw these data: say so
    assert "cross-validation is optimistic" in capsys.readouterr().err

    cfg["train"]["init"] = str(tmp_path / "absent.npz")
    with pytest.raises(ModelFileError, match="absent.npz: no such model file"):
        train(cfg, tmp_path / "absent", progress=False)
    with pytest.raises(ValueError, match="train.init must be"):
        load_config("learning/configs/default.toml", ["train.init=3"])


def test_fine_tuning_keeps_the_init_models_filter_unless_the_configuration_sets_a_key(capsys):
    """The shipped model fine-tuned with default.toml (no [ekf] keys) stays in its own filter, and says so; a key
    the configuration sets wins (hk_finetune.toml's vertical noise over the transfer base's default filter)."""
    from learning.train import adopt_init
    from lfgnss.solve import DEFAULT_MODEL

    own = {"q_vel_up_m2_s3": 0.1, "doppler_sigma_m_s": 0.1, "doppler_cn0_ref_dbhz": 45.0}
    assert adopt_init(load_config("learning/configs/shipped.toml", [f"train.init={DEFAULT_MODEL}"]))["ekf"] == own
    assert "fine-tuned in the filter" not in capsys.readouterr().err    # its own configuration: nothing to say
    assert adopt_init(load_config("learning/configs/default.toml", [f"train.init={DEFAULT_MODEL}"]))["ekf"] == own
    err = capsys.readouterr().err
    assert "fine-tuned in the filter" in err and "ekf.q_vel_up_m2_s3 = 0.1" in err
    mine = adopt_init(load_config("learning/configs/default.toml",
                                  [f"train.init={DEFAULT_MODEL}", "ekf.doppler_sigma_m_s=0.3"]))["ekf"]
    assert mine == own | {"doppler_sigma_m_s": 0.3}
    assert adopt_init(load_config("learning/configs/hk_finetune.toml"))["ekf"] == {"q_vel_up_m2_s3": 0.002}


def test_loss_balance_weighs_each_dataset_by_its_plain_ekf_error():
    """loss.balance = "plain_ekf": factor c / s_d, s_d the plain EKF's 3D RMSE on dataset d, c their geometric mean."""
    import estimators
    from estimators.models import EkfConfig
    from learning.train import dataset_balance
    from lfgnss.simulate import simulate_sequence

    easy = [simulate_sequence(120, nlos_fraction=0.0, seed=s, name=f"easy/{s}") for s in (1, 2)]
    hard = [simulate_sequence(120, nlos_fraction=0.5, seed=3, name="hard/3")]
    k = dataset_balance(easy + hard, ["easy", "easy", "hard"], EkfConfig())

    def rmse(seqs):
        err = [estimators.create("plain-ekf").solve(q).pos_ecef_m - q.truth_ecef_m for q in seqs]
        return float(np.sqrt(np.mean(np.concatenate([np.sum(e ** 2, axis=1) for e in err]))))

    s_easy, s_hard = rmse(easy), rmse(hard)
    assert s_hard > s_easy
    assert k["easy"] == pytest.approx(np.sqrt(s_hard / s_easy)) and k["hard"] == pytest.approx(np.sqrt(s_easy / s_hard))


def test_loss_balance_with_one_dataset_changes_nothing(config, tmp_path):
    """One dataset: its factor is 1, so the run is the unbalanced one to the last bit."""
    import copy

    runs = []
    for balance in ("none", "plain_ekf"):
        cfg = copy.deepcopy(config)
        cfg["train"]["epochs"] = 1
        cfg["loss"]["balance"] = balance
        prep = prepare(cfg)
        assert (prep.window_scale is None) == (balance == "none")
        if prep.window_scale is not None:
            assert np.all(prep.window_scale == 1.0)
        runs.append(train(cfg, tmp_path / balance, progress=False, prepared=prep))
    assert runs[0][1]["train_loss"] == runs[1][1]["train_loss"]
    with pytest.raises(ValueError, match="loss.balance must be 'none' or 'plain_ekf'"):
        load_config("learning/configs/default.toml", ['loss.balance="per_dataset"'])


def test_frozen_parts_keep_their_initial_weights(config, full_run, tmp_path):
    """train.freeze: the named network parts keep the train.init weights; the others are trained; a part the
    network lacks is one clear error naming the setting."""
    import copy

    out, _ = full_run
    start = load_model(out / "model.npz")
    cfg = copy.deepcopy(config)
    cfg["train"].update(init=str(out / "model.npz"), epochs=1, lr=1e-2, select="last",
                        freeze=["embed", "attention", "norm"])
    train(cfg, tmp_path / "frozen", progress=False)
    tuned = load_model(tmp_path / "frozen" / "model.npz")
    for name, value in start.params.items():
        if name.split(".")[0] in ("embed", "attention", "norm"):
            np.testing.assert_array_equal(tuned.params[name], value, err_msg=name)
        else:
            assert not np.array_equal(tuned.params[name], value), name
    with pytest.raises(ValueError, match=r"^train.freeze must be a list of network parts \(embed, attention, "
                                         r"norm, mlp, head\), got \['encoder'\]$"):
        load_config("learning/configs/default.toml", ["train.freeze=['encoder']"])
    assert load_config("learning/configs/default.toml", ["train.freeze=head"])["train"]["freeze"] == ["head"]


def test_every_config_file_loads():
    """Each file in learning/configs parses with known keys; a bundled init model it names exists."""
    from pathlib import Path

    files = sorted(Path("learning/configs").glob("*.toml"))
    assert len(files) >= 10
    for path in files:
        cfg = load_config(str(path))
        assert cfg["data"]["datasets"] and cfg["train"]["epochs"] >= 1, path
        init = cfg["train"]["init"]
        if init and not init.startswith("runs/"):
            assert model_path(init).is_file(), f"{path}: train.init {init} is not bundled"


def test_training_through_the_smoother(config, prepared, full_run, tmp_path):
    """train.smooth = true: the loss and the validation read the RTS-smoothed positions (learning.torch_ekf)."""
    import copy

    from learning.train import evaluate

    cfg = copy.deepcopy(config)
    cfg["train"]["epochs"] = 1
    cfg["train"]["smooth"] = True
    history = train(cfg, tmp_path, progress=False, prepared=prepared, export=False)
    torch.manual_seed(int(cfg["seed"]))
    untrained = build_model(cfg, len(prepared.feature_names), prepared.normaliser)
    for smooth, want in ((True, history[0]), (False, full_run[1][0])):
        got, _ = evaluate(untrained, prepared.val_batches, n_systems=prepared.n_systems, ekf_cfg=ekf_config(cfg),
                          smooth=smooth)
        assert got == pytest.approx(want["val_rmse_3d_m"], rel=1e-12)
    assert history[0]["val_rmse_3d_m"] != full_run[1][0]["val_rmse_3d_m"]
    assert np.isfinite(history[1]["train_loss"]) and history[1]["train_loss"] != full_run[1][1]["train_loss"]
    with pytest.raises(ValueError, match="train.smooth"):
        load_config("learning/configs/default.toml", ["train.smooth='yes'"])


def test_burn_in_leaves_the_cold_start_of_mid_drive_windows_unscored(config, prepared, tmp_path):
    """data.burn_in: windows cut mid-sequence run their first epochs unscored; a sequence's first window keeps all."""
    import copy

    from learning.data import make_windows

    seqs = load_sequences("synthetic", "train", config)
    plain, burnt = make_windows(seqs, 20, 10), make_windows(seqs, 20, 10, burn_in=8)
    assert [(w.seq_index, w.start) for w in plain] == [(w.seq_index, w.start) for w in burnt]
    assert all(w.burn_in == (8 if w.start else 0) for w in burnt) and any(w.start for w in burnt)
    for bad in (-1, 20):
        with pytest.raises(ValueError, match="burn_in"):
            make_windows(seqs, 20, 10, burn_in=bad)
        with pytest.raises(ValueError, match="data.burn_in must be"):
            load_config("learning/configs/default.toml", SETTINGS + [f"data.burn_in={bad}"])
    piece = seqs[0].subset(slice(0, 40))
    piece.truth_ecef_m[12:] = np.nan                    # labels only in epochs 0-11
    assert [w.start for w in make_windows([piece], 20, 10, burn_in=1)] == [0, 10]
    assert [w.start for w in make_windows([piece], 20, 10, burn_in=2)] == [0]

    cfg = copy.deepcopy(config)
    cfg["data"]["burn_in"] = 8
    cfg["train"]["epochs"] = 1
    prep = prepare(cfg)
    scored = torch.isfinite(prep.train_batch.truth_ecef_m).all(-1)
    before = torch.isfinite(prepared.train_batch.truth_ecef_m).all(-1)
    starts = torch.as_tensor([w.start for w in prep.windows])
    assert not scored[starts > 0, :8].any() and torch.equal(scored[starts == 0], before[starts == 0])
    assert torch.equal(scored[:, 8:], before[:, 8:])
    assert torch.equal(prep.train_batch.pr_m, prepared.train_batch.pr_m)      # the filter still runs them
    history = train(cfg, tmp_path, progress=False, prepared=prep, export=False)
    assert np.isfinite(history[1]["train_loss"])


def test_a_bad_setting_is_one_line_on_the_command_line(capsys):
    """learning.train and learning.crossval name a wrong setting in one line and exit 2, before loading data."""
    from learning.crossval import main as crossval_main

    for entry in (main, crossval_main):
        with pytest.raises(SystemExit) as exit_info:
            entry(["--config", "learning/configs/default.toml", "--set", "data.burn_in=40"])
        assert exit_info.value.code == 2
        err = capsys.readouterr().err
        assert "error: data.burn_in must be a whole number of epochs >= 0 and below data.window (40), got 40" in err
        assert "Traceback" not in err


def test_bad_input_found_while_running_is_one_line_too(capsys, tmp_path):
    """Errors that only show once training starts (no checkpoint, unknown dataset, missing model) are one line, exit 2."""
    from learning.crossval import main as crossval_main

    cases = [(main, ["--resume", "--out", str(tmp_path / "empty")], "last.pt: no checkpoint to resume from"),
             (main, ["--set", 'data.datasets=["nope"]', "--out", str(tmp_path / "a")], "unknown dataset 'nope'; known:"),
             (main, ["--set", f"train.init={tmp_path / 'none.npz'}", "--out", str(tmp_path / "b")], "no such model file"),
             (crossval_main, ["--set", 'data.datasets=["nope"]', "--out", str(tmp_path / "c")], "unknown dataset 'nope'")]
    for entry, argv, expected in cases:
        with pytest.raises(SystemExit) as exit_info:
            entry(argv)
        assert exit_info.value.code == 2
        err = capsys.readouterr().err
        assert expected in err and "Traceback" not in err
        assert len(err.strip().splitlines()) == 1, err


def test_cli_warns_when_the_exported_model_is_the_untrained_network(tmp_path, capsys):
    """lr 0: no epoch beats epoch 0, so model.npz (best on validation) holds no training; the user is told."""
    args = ["--config", "learning/configs/default.toml", "--out", str(tmp_path), "--no-progress"]
    settings = [s for s in SETTINGS if not s.startswith(("train.epochs", "train.lr", "train.eta_min"))]
    settings += ["train.epochs=1", "train.lr=0.0", "train.eta_min=0.0"]
    assert main(args + [x for s in settings for x in ("--set", s)]) == 0
    err = capsys.readouterr().err
    assert "holds no training" in err and str(tmp_path / "model.npz") in err
    assert load_model(tmp_path / "model.npz").metadata["epoch"] == 0


def test_config_file_paths_are_read_next_to_it_then_from_the_current_folder(tmp_path, monkeypatch):
    """data.register and train.init, like base, are found beside the config; the shipped ones stay cwd-relative."""
    folder = tmp_path / "configs"
    folder.mkdir()
    (folder / "my-drive.toml").write_text('id = "x"\n')
    (folder / "mine.toml").write_text(f'base = "{Path("learning/configs/default.toml").resolve()}"\n'
                                      '[data]\nregister = ["my-drive.toml", "elsewhere.toml"]\n'
                                      '[train]\ninit = "lfgnss/data/model/lfgnss-transfer-base.npz"\n')
    repo = Path.cwd()
    monkeypatch.chdir(tmp_path)
    (tmp_path / "elsewhere.toml").write_text('id = "y"\n')                 # in the current folder only
    config = load_config(folder / "mine.toml")
    assert config["data"]["register"] == [str(folder / "my-drive.toml"), "elsewhere.toml"]
    assert config["train"]["init"] == "lfgnss/data/model/lfgnss-transfer-base.npz"     # not beside it: as given
    monkeypatch.chdir(repo)
    assert load_config("learning/configs/hk_finetune.toml")["train"]["init"] == "transfer-base"   # a bundled name
    assert load_config(None, ["data.register=my.toml"])["data"]["register"] == ["my.toml"]   # one file, not letters
    recorded = _files_absolute(load_config(None, ["train.init=lfgnss/data/model/lfgnss-default.npz",
                                                  "data.register=learning/configs/../../README.md"]))
    assert recorded["train"]["init"] == str(repo / "lfgnss/data/model/lfgnss-default.npz")   # as runs record them
    assert recorded["data"]["register"] == [str(repo / "README.md")]          # resolved: one file, one spelling
    assert _files_absolute(load_config(None, ["train.init=transfer-base"]))["train"]["init"] == "transfer-base"
    with pytest.raises(ValueError, match="data.register"):
        load_config(None, ["data.register=[1, 2]"])


def test_a_run_from_before_loss_up_weight_resumes(tmp_path):
    """Checkpoints hold their run's config; one saved before loss.up_weight existed must still resume."""
    args = ["--config", "learning/configs/default.toml", "--out", str(tmp_path), "--no-progress"]
    settings = [s for s in SETTINGS if not s.startswith("train.epochs")] + ["train.epochs=1"]
    assert main(args + [x for s in settings for x in ("--set", s)]) == 0
    saved = torch.load(tmp_path / "last.pt", weights_only=False)
    del saved["config"]["loss"]["up_weight"]
    torch.save(saved, tmp_path / "last.pt")
    assert main(args + ["--resume", "--set", "train.epochs=2"]) == 0
    assert torch.load(tmp_path / "last.pt", weights_only=False)["history"][-1]["epoch"] == 2


def _noise_of(run_dir, cfg, prepared):
    """(R, v^c) of the network in ``run_dir/last.pt`` on the prepared training windows."""
    model = build_model(cfg, len(prepared.feature_names))
    model.load_state_dict(torch.load(run_dir / "last.pt", weights_only=False)["model"])
    with torch.no_grad():
        return model(prepared.train_batch.features, prepared.train_batch.mask)


def test_compensation_term_pulls_vc_towards_the_true_pseudorange_errors(config, prepared, full_run, tmp_path):
    """loss.vc_weight > 0 adds the per-satellite v^c term: after the same schedule, v^c is nearer to minus the true
    errors of the training epochs than without it; a network that makes v^c inside the filter is refused."""
    import copy

    from learning.loss import compensation_loss, pseudorange_error_m

    cfg = copy.deepcopy(config)
    cfg["loss"]["vc_weight"] = 1.0
    history = train(cfg, tmp_path, progress=False, prepared=prepared)
    assert np.isfinite(history[-1]["train_loss"])
    batch = prepared.train_batch
    usable = batch.mask & torch.isfinite(batch.truth_ecef_m).all(dim=-1)[..., None]
    error = pseudorange_error_m(batch.pr_m, batch.sat_pos_ecef_m, batch.truth_ecef_m, usable, batch.system_index,
                                prepared.n_systems)
    term = {name: float(compensation_loss(_noise_of(out, cfg, prepared)[1], error, usable, batch.system_index,
                                          prepared.n_systems))
            for name, out in (("with", tmp_path), ("without", full_run[0]))}
    assert term["with"] < 0.8 * term["without"], term
    with pytest.raises(ValueError, match="loss.vc_weight needs a network that reads its features alone"):
        load_config("learning/configs/default.toml", ["loss.vc_weight=0.5", "model.innovation=true"])
    with pytest.raises(ValueError, match="model.compensation = false has none"):
        load_config("learning/configs/default.toml", ["loss.vc_weight=0.5", "model.compensation=false"])
    with pytest.raises(ValueError, match="loss.vc_delta_m"):
        load_config("learning/configs/default.toml", ["loss.vc_delta_m=0"])
    cfg["train"]["epochs"] = 1                   # with loss.balance the term is scaled too: one dataset, factor 1
    runs = [train(cfg, tmp_path / "none", progress=False, prepared=prepared)]
    cfg["loss"]["balance"] = "plain_ekf"
    runs.append(train(cfg, tmp_path / "balanced", progress=False, prepared=prepare(cfg)))
    assert runs[0][1]["train_loss"] == runs[1][1]["train_loss"]


def test_variance_term_fits_r_to_the_errors_left_after_compensation(config, prepared, full_run, tmp_path):
    """loss.r_weight > 0 adds the per-satellite Gaussian NLL of R: after the same schedule that term is lower on the
    training epochs than without it; a network that makes R inside the filter is refused, a negative weight too."""
    from learning.loss import labelled_errors_m, variance_loss

    cfg = copy.deepcopy(config)
    cfg["loss"]["r_weight"] = 1.0
    history = train(cfg, tmp_path, progress=False, prepared=prepared)
    assert np.isfinite(history[-1]["train_loss"])
    batch = prepared.train_batch
    usable, error = labelled_errors_m(batch, prepared.n_systems)
    term = {name: float(variance_loss(*_noise_of(out, cfg, prepared), error, usable, batch.system_index,
                                      prepared.n_systems))
            for name, out in (("with", tmp_path), ("without", full_run[0]))}
    assert term["with"] < term["without"] - 0.1, term
    with pytest.raises(ValueError, match="loss.r_weight needs a network that reads its features alone"):
        load_config("learning/configs/default.toml", ["loss.r_weight=0.5", "model.innovation=true"])
    with pytest.raises(ValueError, match="loss.r_weight"):
        load_config("learning/configs/default.toml", ["loss.r_weight=-1"])
    with pytest.raises(ValueError, match=r"model.r_floor_m2 must be a finite number >= 1e-06, got 0"):
        load_config("learning/configs/default.toml", ["loss.r_weight=1", "model.r_floor_m2=0"])
    with pytest.raises(ValueError, match=r"model.r_floor_m2 must be a finite number >= 1e-06, got 1e-10"):
        load_config("learning/configs/default.toml", ["model.r_floor_m2=1e-10"])     # the plug-in EKF refuses it
    with pytest.raises(ValueError, match=r"loss.r_clock must be 'median' or 'strongest', got 'mean'"):
        load_config("learning/configs/default.toml", ["loss.r_weight=1", "loss.r_clock='mean'"])
    cfg["loss"]["r_clock"], cfg["train"]["epochs"] = "strongest", 1     # the three strongest signals' clock
    plain = train(copy.deepcopy(dict(cfg, loss=dict(cfg["loss"], r_weight=0.0))), tmp_path / "plain", progress=False,
                  prepared=prepared)
    strongest = train(cfg, tmp_path / "strongest", progress=False, prepared=prepared)
    assert np.isfinite(strongest[1]["train_loss"]) and strongest[1]["train_loss"] != plain[1]["train_loss"]


def test_resuming_from_python_says_what_it_ignores_and_a_schedule_taken_past_its_turn(config, prepared, tmp_path):
    """train(config, resume=True) went on with the checkpoint's settings and said nothing of a config that differs;
    extending a run planned to end annealed (epochs <= t_max) past t_max raised the learning rate again silently."""
    cfg = copy.deepcopy(config)
    cfg["train"]["epochs"], cfg["train"]["t_max"] = 1, 1
    train(cfg, tmp_path, progress=False, prepared=prepared)
    changed = copy.deepcopy(cfg)
    changed["train"]["lr"] = 5e-2
    with pytest.warns(UserWarning, match=r"resuming goes on with the checkpoint's configuration, not the one given "
                                         r"\(train.lr 0.01 there, 0.05 given\)") as caught:
        history = train(changed, tmp_path, resume=True, overrides=["train.epochs=2"], progress=False,
                        prepared=prepared)
    assert [h["epoch"] for h in history] == [0, 1, 2] and history[-1]["lr"] != 5e-2
    assert any("goes past train.t_max = 1, where the cosine schedule turns" in str(w.message) for w in caught)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        train(None, tmp_path, resume=True, overrides=["train.epochs=2"], progress=False, prepared=prepared)
    with pytest.raises(ValueError, match="config is None; give a configuration"):
        train(None, tmp_path / "new", progress=False)


def test_a_run_records_its_files_absolute_and_resumes_from_python_with_them_as_given(config, prepared, tmp_path,
                                                                                     monkeypatch):
    """Review: recorded absolute, data.register given relative again on resume warned of a config other than the
    checkpoint's."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "mine.toml").write_text('id = "mine"\n')             # not read: the data are synthetic
    cfg = copy.deepcopy(config)
    cfg["train"]["epochs"], cfg["data"]["register"] = 1, ["mine.toml"]
    train(cfg, tmp_path / "run", progress=False, prepared=prepared)
    saved = torch.load(tmp_path / "run" / "last.pt", weights_only=False)
    assert saved["config"]["data"]["register"] == [str(tmp_path / "mine.toml")]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        train(cfg, tmp_path / "run", resume=True, overrides=["train.epochs=2"], progress=False, prepared=prepared)
