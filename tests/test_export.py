"""Model file: numpy forward == torch forward, round trip, corrupt files, feature checks."""
import json
import warnings
import zipfile

import numpy as np
import pytest
import torch

from learning.export import FORMAT_VERSION, LfgnssModel, ModelFileError, export_model, load_model
from learning.network import LfgnssNet
from learning.normalise import Normaliser, select_features
from lfgnss.errors import InputError
from lfgnss.sequence import DEFAULT_FEATURES
from lfgnss.simulate import simulate_sequence


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A randomly initialised network saved as a checkpoint and exported."""
    tmp = tmp_path_factory.mktemp("export")
    seq = simulate_sequence(30, seed=3, n_slots=16)
    norm = Normaliser.fit([seq], DEFAULT_FEATURES)
    torch.manual_seed(1)
    net = LfgnssNet(len(DEFAULT_FEATURES), r_floor_m2=0.02, r_scale_m2=3.0, r_init_m2=20.0)
    with torch.no_grad():                       # make v^c and R vary visibly
        for p in net.parameters():
            p.add_(0.1 * torch.randn_like(p))
    ckpt = tmp / "best.pt"
    torch.save({"model": net.state_dict(), "model_hparams": net.hyperparameters(), "normaliser": norm.to_dict(),
                "config": {"seed": 0}, "epoch": 3, "history": [{"epoch": 3, "val_rmse_3d_m": 4.2}],
                "data_fingerprints": [{"dataset": "synthetic", "sha256_16": "abc"}]}, ckpt)
    path = export_model(ckpt, tmp / "model.npz")
    return path, net, norm, seq


def test_numpy_predict_matches_torch(exported):
    path, net, norm, seq = exported
    model = load_model(path)
    raw = select_features(seq, model.feature_names)
    mask = seq.mask.copy()
    mask[5] = False                              # an epoch with no satellite
    r_np, vc_np = model.predict(raw, mask)
    x = torch.as_tensor(norm.apply(raw, mask))
    net64 = LfgnssNet(**net.hyperparameters()).double().eval()
    net64.load_state_dict(net.state_dict())
    # weights are stored as float32; compare with the float32 weights run in float64
    with torch.no_grad():
        r_t, vc_t = net64(x, torch.as_tensor(mask))
        r32, vc32 = net.eval()(x.float(), torch.as_tensor(mask))
    np.testing.assert_allclose(r_np, r_t.numpy(), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(vc_np, vc_t.numpy(), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(r_np, r32.numpy(), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(vc_np, vc32.numpy(), rtol=1e-5, atol=1e-5)
    assert np.all(np.isfinite(r_np)) and np.all(r_np[5] == 1.0) and np.all(vc_np[5] == 0.0)


def test_round_trip_metadata_and_noise_model_call(exported):
    path, net, norm, seq = exported
    model = load_model(path, expected_features=DEFAULT_FEATURES)
    assert isinstance(model, LfgnssModel)
    assert model.feature_names == DEFAULT_FEATURES
    np.testing.assert_array_equal(model.normaliser.mean, norm.mean)
    meta = model.metadata
    assert meta["format_version"] == FORMAT_VERSION and meta["epoch"] == 3 and meta["val_rmse_3d_m"] == 4.2
    assert meta["data_fingerprints"][0]["dataset"] == "synthetic" and "torch" in meta["versions"]
    r, vc = model(seq)                           # estimators NoiseModel protocol
    assert r.shape == seq.mask.shape and vc.shape == seq.mask.shape
    # features are picked by NAME: a sequence with extra / reordered columns gives the same result
    from dataclasses import replace
    names = ("extra",) + tuple(reversed(seq.feature_names))
    feats = np.concatenate([np.ones(seq.features.shape[:2] + (1,)), seq.features[..., ::-1]], axis=-1)
    r2, vc2 = model(replace(seq, features=feats, feature_names=names))
    np.testing.assert_array_equal(r, r2)
    np.testing.assert_array_equal(vc, vc2)


def test_truncated_and_garbage_files_fail_clearly(exported, tmp_path):
    path = exported[0]
    data = path.read_bytes()
    bad = tmp_path / "truncated.npz"
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(ModelFileError, match="truncated.npz") as info:
        load_model(bad)
    assert "\n" not in str(info.value)
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a model at all")
    with pytest.raises(ValueError, match="junk.npz"):
        load_model(junk)
    with pytest.raises(ModelFileError, match="no such"):
        load_model(tmp_path / "missing.npz")


def _rewrite_metadata(src, dst, change):
    with np.load(src, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["metadata"]))
    change(meta)
    arrays["metadata"] = np.array(json.dumps(meta))
    np.savez(dst, **arrays)


def test_wrong_format_version(exported, tmp_path):
    dst = tmp_path / "v99.npz"
    _rewrite_metadata(exported[0], dst, lambda m: m.update(format_version=99))
    with pytest.raises(ModelFileError, match="format version 99"):
        load_model(dst)


def test_mismatched_features(exported, tmp_path):
    path, _, _, seq = exported
    no_dpc = DEFAULT_FEATURES[:4]
    with pytest.raises(ModelFileError, match="do not match"):
        load_model(path, expected_features=no_dpc)
    from dataclasses import replace
    model = load_model(path)
    with pytest.raises(ValueError, match="dpc_gdop"):
        model(replace(seq, features=seq.features[..., :4], feature_names=no_dpc))


@pytest.mark.parametrize("bogus", [["snr_db"], ["snr_db", "multipath_index"]])
def test_unknown_feature_names_file_and_feature(exported, tmp_path, bogus):
    """A model needing features this lfgnss cannot compute fails at load time, naming the file and features."""
    dst = tmp_path / "unknown_feature.npz"

    def change(meta):
        for i, name in enumerate(bogus):
            meta["feature_names"][i] = name
            meta["normaliser"]["feature_names"][i] = name

    _rewrite_metadata(exported[0], dst, change)
    with pytest.raises(ModelFileError) as info:
        load_model(dst)
    message = str(info.value)
    assert message.startswith(f"{dst}: the model needs feature(s) {', '.join(bogus)} ") and "\n" not in message
    assert isinstance(info.value, InputError) and isinstance(info.value, ValueError)


def test_feature_names_not_a_list_of_names(exported, tmp_path):
    dst = tmp_path / "bad_names.npz"
    _rewrite_metadata(exported[0], dst, lambda m: m.update(feature_names="cn0"))
    with pytest.raises(ModelFileError, match=rf"^{dst}: feature_names is not a list of names"):
        load_model(dst)


def test_file_is_a_single_npz_without_pickles(exported):
    with zipfile.ZipFile(exported[0]) as z:
        names = z.namelist()
    assert "metadata.npy" in names and any(n.startswith("param/") for n in names)
    np.load(exported[0], allow_pickle=False)["metadata"]


def test_prior_network_untrained_equals_heuristic_and_exports(tmp_path):
    """With model.r_prior the untrained head (o_R = 0) gives the plain EKF's noise; numpy export agrees."""
    from estimators.noise import HeuristicNoise
    from learning.network import heuristic_prior

    seq = simulate_sequence(40, seed=5, n_slots=16)
    norm = Normaliser.fit([seq], DEFAULT_FEATURES)
    prior = heuristic_prior(norm.feature_names, norm.mean, norm.std)
    net = LfgnssNet(len(DEFAULT_FEATURES), r_floor_m2=1e-6, r_prior=prior).double().eval()    # the least floor
    with torch.no_grad():
        net.head.weight.zero_()
        net.head.bias.zero_()
    x = torch.as_tensor(norm.apply(select_features(seq, DEFAULT_FEATURES), seq.mask))
    with torch.no_grad():
        r, vc = net(x, torch.as_tensor(seq.mask))
    expected, _ = HeuristicNoise()(seq)
    np.testing.assert_allclose(r.numpy()[seq.mask] - 1e-6, expected[seq.mask], rtol=1e-9)
    assert np.all(vc.numpy() == 0.0)

    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.1 * torch.randn_like(p))
    ckpt = tmp_path / "best.pt"
    torch.save({"model": net.float().state_dict(), "model_hparams": net.hyperparameters(),
                "normaliser": norm.to_dict(), "config": {}, "epoch": 1, "history": []}, ckpt)
    model = load_model(export_model(ckpt, tmp_path / "model.npz"))
    r_np, vc_np = model(seq)
    with torch.no_grad():
        r_t, vc_t = net.float()(x.float(), torch.as_tensor(seq.mask))
    np.testing.assert_allclose(r_np[seq.mask], r_t.numpy()[seq.mask], rtol=1e-4)
    np.testing.assert_allclose(vc_np[seq.mask], vc_t.numpy()[seq.mask], rtol=1e-4, atol=1e-4)


def test_r_only_network_outputs_no_compensation_and_exports(exported, tmp_path):
    """model.compensation = false: v^c is 0 in torch and in the exported file; R is unchanged."""
    _, net, norm, seq = exported
    hp = dict(net.hyperparameters(), compensation=False)
    r_only = LfgnssNet(**hp).eval()
    r_only.load_state_dict(net.state_dict())
    x = torch.as_tensor(norm.apply(select_features(seq, DEFAULT_FEATURES), seq.mask)).float()
    mask = torch.as_tensor(seq.mask)
    with torch.no_grad():
        r_full, vc_full = net.eval()(x, mask)
        r, vc = r_only(x, mask)
    assert torch.equal(r, r_full) and torch.all(vc == 0) and torch.any(vc_full != 0)
    ckpt = tmp_path / "best.pt"
    torch.save({"model": r_only.state_dict(), "model_hparams": r_only.hyperparameters(),
                "normaliser": norm.to_dict(), "config": {}, "epoch": 1, "history": []}, ckpt)
    model = load_model(export_model(ckpt, tmp_path / "model.npz"))
    r_np, vc_np = model(seq)
    assert model.metadata["model"]["compensation"] is False
    np.testing.assert_allclose(r_np[seq.mask], r.numpy()[seq.mask], rtol=1e-5)
    assert np.all(vc_np == 0.0)


def test_online_model_file_needs_innovations(exported, tmp_path):
    """A model trained with ``model.innovation`` is ``online``: ``predict`` requires the innovations."""
    _, _, norm, seq = exported
    net = LfgnssNet(len(DEFAULT_FEATURES), innovation=True)
    ckpt = tmp_path / "best.pt"
    torch.save({"model": net.state_dict(), "model_hparams": net.hyperparameters(), "normaliser": norm.to_dict(),
                "config": {}, "epoch": 1, "history": []}, ckpt)
    model = load_model(export_model(ckpt, tmp_path / "model.npz"))
    raw = select_features(seq, model.feature_names)
    assert model.online and not load_model(exported[0]).online
    r0, _ = model.predict(raw, seq.mask, np.zeros(seq.mask.shape))
    r1, _ = model.predict(raw, seq.mask, np.full(seq.mask.shape, 4.0))
    assert r0.shape == seq.mask.shape and not np.allclose(r0[seq.mask], r1[seq.mask])
    with pytest.raises(ValueError, match="needs innovations"):
        model.predict(raw, seq.mask)
    meta = json.loads(str(np.load(tmp_path / "model.npz")["metadata"]))
    meta["model"]["innovation"] = False          # the embedding no longer fits the inputs the file names
    arrays = dict(np.load(tmp_path / "model.npz"))
    arrays["metadata"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ModelFileError, match="embedding takes 9 inputs but 8"):
        load_model(tmp_path / "bad.npz")


@pytest.mark.parametrize("backend", ["fgo", "wls-weighted"])
def test_online_model_given_to_another_estimator_warns_once_under_its_name(exported, tmp_path, backend):
    """An online model makes its R by an EKF run; given to the factor graph or the weighted fix, R in another unit is
    said once, by the estimator given it, not again under the EKF's name."""
    if backend == "fgo":
        pytest.importorskip("gtsam")
    from estimators import NoiseWarning, create

    _, _, norm, seq = exported
    ckpt, net = tmp_path / "online.pt", LfgnssNet(len(DEFAULT_FEATURES), innovation=True)
    torch.save({"model": net.state_dict(), "model_hparams": net.hyperparameters(), "normaliser": norm.to_dict(),
                "config": {}, "epoch": 1, "history": []}, ckpt)
    model = load_model(export_model(ckpt, tmp_path / "online.npz"))
    given = model.predict
    model.predict = lambda *args, **kw: (lambda r, vc: (r * 1e4, vc))(*given(*args, **kw))     # R in cm^2
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        estimator = create(backend, noise=model)
        estimator.solve(seq)
    said = [str(w.message) for w in caught if "R is a variance in m^2" in str(w.message)
            and issubclass(w.category, NoiseWarning)]
    assert len(said) == 1 and not said[0].startswith("LfgnssEkf"), said
