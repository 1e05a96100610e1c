"""Ensemble model files: several seeds' networks of one recipe run as one noise model (learning.export)."""
import json
import re

import numpy as np
import pytest
import torch

from learning.export import (ENSEMBLE_FORMAT_VERSION, FORMAT_VERSION, ModelFileError, export_ensemble, export_model,
                             load_model, main, trained_on)
from learning.network import LfgnssNet, NetworkEnsemble, combine_members
from learning.normalise import Normaliser, select_features
from lfgnss.sequence import DEFAULT_FEATURES
from lfgnss.simulate import simulate_sequence

CONFIG = {"seed": 0, "train": {"lr": 1e-3}, "data": {"datasets": ["synthetic"], "train_split": "train"}}


def _checkpoint(path, seed: int, norm: Normaliser, config: dict | None = None, **saved) -> tuple:
    """A checkpoint of a network initialised with ``seed`` (weights moved so that R and v^c vary); ``saved`` replaces
    or adds checkpoint keys."""
    torch.manual_seed(seed)
    net = LfgnssNet(len(DEFAULT_FEATURES), r_floor_m2=0.02, r_scale_m2=3.0, r_init_m2=20.0)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.1 * torch.randn_like(p))
    config = {**CONFIG, "seed": seed} if config is None else config
    torch.save({"model": net.state_dict(), "model_hparams": net.hyperparameters(), "normaliser": norm.to_dict(),
                "config": config, "epoch": 3 + seed, "history": [{"epoch": 3 + seed, "val_rmse_3d_m": 4.0 + seed}],
                "data_fingerprints": [{"dataset": "synthetic", "sha256_16": "abc"}], **saved}, path)
    return path, net


@pytest.fixture(scope="module")
def members(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ensemble")
    seq = simulate_sequence(30, seed=3, n_slots=16)
    norm = Normaliser.fit([seq], DEFAULT_FEATURES)
    runs = [_checkpoint(tmp / f"s{s}.pt", s, norm) for s in (0, 1, 2)]
    return tmp, seq, norm, runs


def test_an_ensemble_file_gives_the_geometric_mean_of_its_members_r_and_the_mean_of_their_vc(members):
    tmp, seq, norm, runs = members
    ensemble = load_model(export_ensemble([p for p, _ in runs], tmp / "ens.npz"))
    singles = [load_model(export_model(p, tmp / f"{p.stem}.npz")) for p, _ in runs]
    raw, mask = select_features(seq, DEFAULT_FEATURES), seq.mask
    r, vc = ensemble.predict(raw, mask)
    each = [m.predict(raw, mask) for m in singles]
    np.testing.assert_allclose(r, np.exp(np.mean([np.log(e[0]) for e in each], axis=0)), rtol=1e-12)
    np.testing.assert_allclose(vc, np.mean([e[1] for e in each], axis=0), rtol=1e-12, atol=1e-12)
    assert not np.allclose(each[0][0], each[1][0])               # the members differ: the test means something
    x = torch.as_tensor(norm.apply(raw, mask))                   # the torch ensemble that learning.crossval scores
    nets = []
    for _, net in runs:
        net64 = LfgnssNet(**net.hyperparameters()).double().eval()
        net64.load_state_dict(net.state_dict())
        nets.append(net64)
    with torch.no_grad():
        r_t, vc_t = NetworkEnsemble(nets)(x, torch.as_tensor(mask))
    np.testing.assert_allclose(r, r_t.numpy(), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(vc, vc_t.numpy(), rtol=1e-9, atol=1e-9)


def test_the_mixture_combination_is_the_moment_matched_mixture_of_the_members_gaussians():
    """Two members N(vc_m, R_m) with equal weight: the mixture's mean is the mean of v^c, its variance the mean R plus
    the v^c spread (here (1 + 3) / 2 + 2^2 = 6 m^2); members that agree keep their arithmetic-mean R."""
    r = [torch.tensor([1.0, 4.0]), torch.tensor([3.0, 4.0])]
    vc = [torch.tensor([-1.0, 0.5]), torch.tensor([3.0, 0.5])]
    r_mix, vc_mix = combine_members(r, vc, "mixture")
    assert r_mix.tolist() == [6.0, 4.0] and vc_mix.tolist() == [1.0, 0.5]
    rng = np.random.default_rng(0)                               # against samples of the mixture itself
    draws = np.concatenate([rng.normal(m, np.sqrt(v), 200_000) for m, v in ((-1.0, 1.0), (3.0, 3.0))])
    assert draws.var() == pytest.approx(6.0, rel=0.02)
    r_geo, _ = combine_members(r, vc)
    assert r_geo.tolist() == pytest.approx([3 ** 0.5, 4.0])
    with pytest.raises(ValueError, match="ensemble combination 'median': expected one of geometric, mixture"):
        combine_members(r, vc, "median")
    with pytest.raises(ValueError, match="ensemble combination 'median'"):
        NetworkEnsemble([LfgnssNet(len(DEFAULT_FEATURES))], combine="median")


def test_an_ensemble_is_format_version_2_and_records_each_member(members):
    tmp, _, _, runs = members
    model = load_model(export_ensemble([p for p, _ in runs], tmp / "e2.npz"))
    meta = model.metadata
    assert meta["format_version"] == ENSEMBLE_FORMAT_VERSION and len(model.members) == 3
    assert [(m["seed"], m["epoch"], m["val_rmse_3d_m"]) for m in meta["ensemble"]["members"]] == \
        [(0, 3, 4.0), (1, 4, 5.0), (2, 5, 6.0)]
    single = load_model(export_ensemble([runs[0][0]], tmp / "one.npz"))      # one checkpoint: a plain file
    assert single.metadata["format_version"] == FORMAT_VERSION and len(single.members) == 1
    assert "ensemble" not in single.metadata
    assert trained_on(meta) == "synthetic (train), 3 seeds" and trained_on(single.metadata) == "synthetic (train)"


@pytest.mark.parametrize("damage, message", [
    (lambda meta, arrays: meta.pop("ensemble"), "metadata ensemble.members must list two or more networks"),
    (lambda meta, arrays: meta["ensemble"]["members"].pop(), "array member2/param/attention.in_proj_bias belongs to "
                                                            "no network its metadata lists (2; ensemble.members)"),
    (lambda meta, arrays: arrays.pop("member1/param/head.bias"), "parameter 'member1/head.bias' missing"),
    (lambda meta, arrays: meta.update(format_version=FORMAT_VERSION), "metadata ensemble in a format version 1"),
])
def test_a_damaged_ensemble_file_is_one_line_naming_it(members, tmp_path, damage, message):
    tmp, _, _, runs = members
    path = export_ensemble([p for p, _ in runs], tmp_path / "e.npz")
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["metadata"]))
    damage(meta, arrays)
    arrays["metadata"] = np.array(json.dumps(meta))
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ModelFileError) as info:
        load_model(tmp_path / "bad.npz")
    assert message in str(info.value) and "bad.npz" in str(info.value) and "\n" not in str(info.value)


def test_members_of_other_recipes_or_data_or_the_same_run_twice_are_refused(members, tmp_path):
    tmp, seq, norm, runs = members
    other_lr = _checkpoint(tmp_path / "lr.pt", 5, norm, {**CONFIG, "seed": 5, "train": {"lr": 3e-4}})[0]
    same_seed = _checkpoint(tmp_path / "again.pt", 0, norm)[0]
    no_seed = _checkpoint(tmp_path / "none.pt", 7, norm, {k: v for k, v in CONFIG.items() if k != "seed"})[0]
    other_data = _checkpoint(tmp_path / "data.pt", 6, Normaliser.fit([simulate_sequence(30, seed=9, n_slots=16)],
                                                                      DEFAULT_FEATURES))[0]
    for paths, message in (([runs[0][0], other_lr], "lr.pt: config train.lr differs from"),
                           ([runs[0][0], other_data], "data.pt: the normaliser (the training data's feature "
                                                      "statistics) differs"),
                           ([runs[0][0], runs[0][0]], "s0.pt: given twice"),
                           ([runs[0][0], same_seed], "again.pt: has the seed of "),
                           ([runs[0][0], no_seed], "none.pt: records no seed")):
        with pytest.raises(ModelFileError) as info:
            export_ensemble(paths, tmp_path / "x.npz")
        assert message in str(info.value)
    assert not (tmp_path / "x.npz").exists()


def test_the_command_writes_shows_and_refilters_an_ensemble(members, tmp_path, capsys):
    _, seq, _, runs = members
    out = tmp_path / "ens.npz"
    assert main([*(str(p) for p, _ in runs), str(out)]) == 0
    assert "ens.npz: ensemble of 3 networks" in capsys.readouterr().out
    assert main(["--show", str(out)]) == 0
    shown = capsys.readouterr().out
    assert "ensemble of 3 networks of one recipe (R: geometric mean" in shown
    assert "  2: seed 2, epoch 5, validation 3D RMSE 6.000 m" in shown
    put_together = next(line for line in shown.splitlines() if line.startswith("  put together "))
    assert put_together.endswith(f"python -m learning.export {' '.join(str(p) for p, _ in runs)} {out}")
    refiltered = tmp_path / "gated.npz"                      # a filter change keeps every member
    assert main([str(out), str(refiltered), "--ekf", "gate_sigma=2.5"]) == 0
    capsys.readouterr()
    a, b = load_model(out), load_model(refiltered)
    assert len(b.members) == 3 and b.metadata["ekf_config"]["gate_sigma"] == 2.5
    np.testing.assert_array_equal(a.predict(select_features(seq, DEFAULT_FEATURES), seq.mask)[0],
                                  b.predict(select_features(seq, DEFAULT_FEATURES), seq.mask)[0])
    for argv, message in (([str(runs[0][0]), str(runs[1][0]), str(tmp_path / "y.npz"), "--ekf", "gate_sigma=2"],
                           "--ekf takes one source"),
                          ([str(runs[0][0]), str(out), str(tmp_path / "y.npz")],
                           f"ens.npz: has the seed of {runs[0][0]}: an ensemble's members are runs of one recipe"),
                          ([str(out), str(tmp_path / "y.npz")],
                           "ens.npz: a model file, not a training checkpoint: give --ekf KEY=VALUE to write it with "
                           "another filter setting, checkpoints of other seeds to grow it into an ensemble")):
        with pytest.raises(SystemExit) as info:
            main(argv)
        err = capsys.readouterr().err
        assert info.value.code == 2 and message in err.strip().splitlines()[-1] and "Traceback" not in err


def test_a_model_file_grows_by_the_seeds_trained_since_as_if_all_were_exported_at_once(members, tmp_path, capsys):
    """A shipped ensemble whose checkpoints are gone takes new seeds' checkpoints: the same networks, records and noise
    as one export of every checkpoint; a seed it holds, another filter or a lone network is one line naming the file."""
    _, seq, _, runs = members
    raw, mask = select_features(seq, DEFAULT_FEATURES), seq.mask
    first_two = export_ensemble([runs[0][0], runs[1][0]], tmp_path / "two.npz")
    grown = load_model(export_ensemble([first_two, runs[2][0]], tmp_path / "grown.npz"))
    at_once = load_model(export_ensemble([p for p, _ in runs], tmp_path / "once.npz"))
    for a, b in zip(grown.predict(raw, mask), at_once.predict(raw, mask)):
        np.testing.assert_array_equal(a, b)
    records = grown.metadata["ensemble"]["members"]
    assert [(m["seed"], m["checkpoint"], m.get("model_file")) for m in records] == \
        [(0, str(runs[0][0]), str(first_two)), (1, str(runs[1][0]), str(first_two)), (2, str(runs[2][0]), None)]
    assert main(["--show", str(tmp_path / "grown.npz")]) == 0
    shown = capsys.readouterr().out
    assert f"  1: seed 1, epoch 4, validation 3D RMSE 5.000 m ({runs[1][0]}, via {first_two})" in shown
    single = export_model(runs[0][0], tmp_path / "s0.npz")               # a single-network file grows too
    assert len(load_model(export_ensemble([single, runs[1][0]], tmp_path / "pair.npz")).members) == 2
    gated = tmp_path / "gated.npz"
    assert main([str(first_two), str(gated), "--ekf", "gate_sigma=2.5"]) == 0
    for sources, message in (([first_two, runs[1][0]], f"s1.pt: has the seed of {first_two}"),
                             ([gated, runs[2][0]], f"s2.pt: ekf_config differs from {gated}'s"),
                             ([single], "s0.npz: holds one network: an ensemble needs two or more")):
        with pytest.raises(ModelFileError) as info:
            export_ensemble(sources, tmp_path / "x.npz")
        assert message in str(info.value) and "\n" not in str(info.value)
    assert not (tmp_path / "x.npz").exists()


def test_runs_of_the_same_files_on_another_machine_join_though_their_features_differ_in_rounding(members, tmp_path):
    """Features computed on two machines differ by ~1e-11 of their spread, so the sequences' hashes differ: the same
    input files (SHA-256), sequences and statistics within Normaliser.SAME_TOL still make one ensemble; other input
    files or statistics beyond rounding do not."""
    _, _, norm, _ = members
    files = {"synthetic": {"drive.obs": "1111", "truth.txt": "2222"}}
    here = _checkpoint(tmp_path / "here.pt", 0, norm, data_fingerprints=[{"sequence": "s/train", "sha256_16": "aa"}],
                       source_files=files)[0]

    def elsewhere(name, seed, shift, **saved):
        moved = Normaliser(norm.feature_names, norm.mean + shift * norm.std, norm.std * (1 + shift))
        saved = {"data_fingerprints": [{"sequence": "s/train", "sha256_16": "bb"}], "source_files": files, **saved}
        return _checkpoint(tmp_path / name, seed, moved, **saved)[0]

    model = load_model(export_ensemble([here, elsewhere("there.pt", 1, 1e-11)], tmp_path / "e.npz"))
    assert len(model.members) == 2
    for path, message in ((elsewhere("far.pt", 2, 1e-6), "far.pt: the normaliser (the training data's feature "
                                                         "statistics) differs"),
                          (elsewhere("other.pt", 3, 0.0, source_files={"synthetic": {"drive.obs": "3333"}}),
                           "other.pt: data_fingerprints differs"),
                          (elsewhere("longer.pt", 4, 0.0, data_fingerprints=[{"sequence": "s/train+val",
                                                                              "sha256_16": "bb"}]),
                           "longer.pt: data_fingerprints differs")):
        with pytest.raises(ModelFileError, match=re.escape(message)):
            export_ensemble([here, path], tmp_path / "x.npz")


def test_an_ensemble_runs_in_the_ekf_and_cannot_start_a_fine_tuning(members, tmp_path):
    import estimators
    from learning.train import init_model

    tmp, seq, _, runs = members
    path = export_ensemble([p for p, _ in runs], tmp_path / "ens.npz")
    sol = estimators.create("ekf", noise=str(path)).solve(seq)
    assert np.all(np.isfinite(sol.pos_ecef_m[sol.available]))
    with pytest.raises(ValueError, match="is an ensemble of 3 networks; fine-tuning starts from one network"):
        init_model({"train": {"init": str(path)}})



def test_runs_that_name_their_files_otherwise_still_make_one_ensemble(members, tmp_path):
    """A dataset TOML or init model named by another path (a run started in another folder) is the same recipe: the
    files' contents are compared (data fingerprints, the init model's SHA-256), not their names."""
    _, _, norm, runs = members
    moved = {**CONFIG, "seed": 8, "data": {**CONFIG["data"], "register": ["../elsewhere/drive.toml"]}}
    other = _checkpoint(tmp_path / "moved.pt", 8, norm, moved)[0]
    model = load_model(export_ensemble([runs[0][0], other], tmp_path / "e.npz"))
    assert len(model.members) == 2


def test_an_ensemble_grown_in_place_keeps_where_its_networks_came_from(members, tmp_path, capsys):
    """Growing a model file onto itself (the shipped-model workflow): the file it grew from is kept in
    ``ensemble.grown_from`` with its SHA-256 and how it was put together, each network keeps the first file it came
    through, and the written file's time and versions are the growth's; ``--show`` prints it all."""
    import hashlib

    _, _, _, runs = members
    grown = tmp_path / "model.npz"
    assert main([str(runs[0][0]), str(runs[1][0]), str(grown)]) == 0
    before = load_model(grown).metadata
    sha = hashlib.sha256(grown.read_bytes()).hexdigest()[:16]
    assert main([str(grown), str(runs[2][0]), str(grown)]) == 0                   # in place, from the command line
    assert "model.npz: ensemble of 3 networks" in capsys.readouterr().out
    meta = load_model(grown).metadata
    ensemble = meta["ensemble"]
    assert [(m["seed"], m.get("model_file"), m.get("model_file_sha256_16")) for m in ensemble["members"]] == \
        [(0, str(grown), sha), (1, str(grown), sha), (2, None, None)]
    (source,) = ensemble["grown_from"]
    assert source["model_file"] == str(grown) and source["sha256_16"] == sha and source["networks"] == 2
    assert source["exported"] == before["ensemble"]["exported"]
    assert meta["created_utc"] == ensemble["exported"]["created_utc"] >= before["created_utc"]
    again = tmp_path / "again.npz"                                              # a second growth keeps the first
    export_ensemble([grown, _checkpoint(tmp_path / "s7.pt", 7, members[2])[0]], again)
    meta = load_model(again).metadata
    assert [m.get("model_file") for m in meta["ensemble"]["members"]] == [str(grown)] * 3 + [None]
    assert meta["ensemble"]["grown_from"][0]["grown_from"] == [source]
    assert main(["--show", str(again)]) == 0
    shown = capsys.readouterr().out
    assert f"  grown from {grown} (sha256 " in shown and f"    grown from {grown} (sha256 {sha}..., 2 networks" in shown
    single = export_model(runs[0][0], tmp_path / "single.npz")                   # a lone network records no checkpoint
    meta = load_model(export_ensemble([single, runs[1][0]], tmp_path / "pair.npz")).metadata
    assert meta["ensemble"]["members"][0]["checkpoint"] is None
    assert main(["--show", str(tmp_path / "pair.npz")]) == 0
    assert f"  0: seed 0, epoch 3, validation 3D RMSE 4.000 m (checkpoint not recorded, via {single})" in \
        capsys.readouterr().out


def test_a_grown_file_that_does_not_read_back_leaves_the_source_whole(members, tmp_path, monkeypatch):
    import learning.export as export

    _, _, _, runs = members
    path = export_ensemble([runs[0][0], runs[1][0]], tmp_path / "model.npz")
    kept = path.read_bytes()

    def broken(p, *a, **k):
        if ".partial" in str(p):
            raise ModelFileError(p, "does not read back")
        return load_model(p, *a, **k)

    monkeypatch.setattr(export, "load_model", broken)
    with pytest.raises(ModelFileError) as info:
        export_ensemble([path, runs[2][0]], path)
    assert str(info.value).startswith(f"{path}: the file written does not read back, so it was not written (")
    assert path.read_bytes() == kept and [p.name for p in tmp_path.iterdir()] == ["model.npz"]


def test_a_bundled_model_is_a_source_by_name_and_members_from_elsewhere_keep_their_fingerprints(members, tmp_path):
    from lfgnss.paths import bundled_models

    _, _, norm, _ = members
    name = sorted(bundled_models())[0]
    with pytest.raises(ModelFileError) as info:                               # read as the model file, not a checkpoint
        export_ensemble([name, _checkpoint(tmp_path / "s99.pt", 99, norm)[0]], tmp_path / "x.npz")
    assert f"differs from {bundled_models()[name]}'s" in str(info.value)
    files = {"synthetic": {"drive.obs": "1111"}}
    here = _checkpoint(tmp_path / "here.pt", 0, norm, data_fingerprints=[{"sequence": "s", "sha256_16": "aa"}],
                       source_files=files)[0]
    there = _checkpoint(tmp_path / "there.pt", 1, norm, data_fingerprints=[{"sequence": "s", "sha256_16": "bb"}],
                        source_files=files)[0]
    records = load_model(export_ensemble([here, there], tmp_path / "e.npz")).metadata["ensemble"]["members"]
    assert "data_fingerprints" not in records[0] and records[1]["data_fingerprints"] == [{"sequence": "s",
                                                                                         "sha256_16": "bb"}]


def test_an_ensemble_grown_from_a_file_without_spans_takes_a_newer_members(members, tmp_path):
    """A shipped file of before data_spans grown by a new seed's checkpoint: the ensemble records the spans."""
    _, _, norm, _ = members
    spans = [{"dataset": "synthetic", "split": "train", "sequence": "s", "gps_s": [0.0, 9.0], "place_ecef_m": [],
              "radius_m": None}]
    old = _checkpoint(tmp_path / "old.pt", 0, norm)[0]
    new = _checkpoint(tmp_path / "new.pt", 1, norm, data_spans=spans)[0]
    assert "data_spans" not in torch.load(old, weights_only=False)
    assert load_model(export_ensemble([old, new], tmp_path / "e.npz")).metadata["data_spans"] == spans
