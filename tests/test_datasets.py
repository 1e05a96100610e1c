"""Dataset layer: benchmark splits and truth alignment on shared data, user TOML datasets, bad truth lines."""
import numpy as np
import pytest

from lfgnss import datasets
from lfgnss.errors import InputError
from lfgnss.solve import SAMPLE_DIR

# epochs per split from shared/BENCHMARK.md (berlin: 5 Hz epochs with t < 150 s etc.)
EXPECTED = {"hk-tst-2019": {"train": 240, "val": 60, "test": 185},
            "berlin-pp": {"train": 724, "val": 148, "test": 500},
            "hk-tst-static-2020": {"train": 500, "val": 100, "test": 386}}


@pytest.mark.parametrize("dataset_id", sorted(EXPECTED), ids=str)
def test_benchmark_split_alignment(dataset_id):
    spec = datasets.get(dataset_id)
    if spec.missing():
        pytest.skip(f"shared data not found: {spec.missing()[0]}")
    seq = datasets.build(dataset_id)
    counts = {split: int(datasets.split_index(seq, spec, split).sum()) for split in spec.splits}
    assert counts == EXPECTED[dataset_id]
    # aligned truth is close to the coarse fix (tens of metres in these canyons, never kilometres)
    both = np.all(np.isfinite(seq.truth_ecef_m), 1) & np.all(np.isfinite(seq.coarse_ecef_m), 1)
    err = np.linalg.norm(seq.coarse_ecef_m[both] - seq.truth_ecef_m[both], axis=1)
    assert np.median(err) < 120.0
    test = datasets.load_split(dataset_id, "test")
    assert len(test) == 1 and len(test[0]) == EXPECTED[dataset_id]["test"]
    assert np.all(np.isfinite(test[0].truth_ecef_m))


def _user_toml(tmp_path, truth_name="Berlin_Potsdamer_Platz_GT.txt"):
    cfg = tmp_path / "mine.toml"
    cfg.write_text(f'''
id = "my-berlin"
obs = ["{SAMPLE_DIR / 'Berlin_Potsdamer_Platz.obs.gz'}"]
nav = ["{SAMPLE_DIR / 'brdc1580.16n.gz'}", "{SAMPLE_DIR / 'brdc1580.16g.gz'}"]
systems = ["G", "R"]
[truth]
file = "{truth_name}"
format = "smartloc"
time_origin_gps_s = {1900 * 604800 + 126641.7}
[splits]
axis = "relative_s"
train = [0, 100]
val = [100, 120]
test = [120, 300]
''')
    return cfg


def test_user_dataset_from_toml(tmp_path, monkeypatch):
    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))
    (tmp_path / "Berlin_Potsdamer_Platz_GT.txt").write_text((SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt").read_text())
    spec = datasets.register_toml(_user_toml(tmp_path))
    assert spec.id in datasets.registered()
    train = datasets.load_split("my-berlin", "train")
    test = datasets.load_split("my-berlin", "test")
    assert len(train) == 1 and 450 < len(train[0]) < 520
    assert np.all(np.isfinite(test[0].truth_ecef_m))
    assert train[0].time_gps_s[-1] < test[0].time_gps_s[0]
    # second build comes from the cache
    assert list((tmp_path / "cache" / "sequences").glob("my-berlin-*.npz"))


def test_training_registers_user_datasets_named_in_its_config(tmp_path, monkeypatch):
    """learning.train's data.register lets the trainer (and its CLI) load a user dataset by id."""
    from learning.train import load_config, load_sequences

    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(datasets, "_REGISTRY", {})
    (tmp_path / "Berlin_Potsdamer_Platz_GT.txt").write_text((SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt").read_text())
    config = load_config(None, [f'data.register=["{_user_toml(tmp_path)}"]', 'data.datasets=["my-berlin"]'])
    assert "my-berlin" not in datasets.registered()
    val = load_sequences("my-berlin", "val", config)
    assert "my-berlin" in datasets.registered() and len(val) == 1 and 90 < len(val[0]) < 110


def test_truth_file_with_bad_lines(tmp_path):
    lines = (SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt").read_text().splitlines()
    lines[2] = "point3 0.5 37851x5.7 899901.8 5037236.1 0 0 0"
    lines[5] = "garbage"
    lines[6] = "# a comment"
    bad = tmp_path / "gt.txt"
    bad.write_text("\n".join(lines))
    spec = datasets.register_toml(_user_toml(tmp_path, "gt.txt"))
    t = spec.time_origin_gps_s + np.array([0.0, 0.5, 0.7])
    truth, notes = datasets.align_truth(t, spec)
    assert notes == [f"{bad}:3: unreadable truth line, skipped", f"{bad}:6: not a point3 record, skipped"]
    assert np.all(np.isfinite(truth[0])) and np.all(np.isnan(truth[1])) and np.all(np.isfinite(truth[2]))


def test_bad_toml_is_one_line_error(tmp_path):
    cfg = tmp_path / "bad.toml"
    cfg.write_text('id = "x"\nobs = ["a.obs"]\n')
    with pytest.raises(InputError, match="bad.toml: dataset config lacks"):
        datasets.register_toml(cfg)


def test_present_reports_each_dataset_with_missing_files(tmp_path, monkeypatch):
    monkeypatch.setenv("LFGNSS_SHARED_DATA", str(tmp_path))
    lines = []
    assert datasets.present(["hk-tst-2019", "berlin-pp"], lines.append) == []
    assert [line.split(":")[0] for line in lines] == ["hk-tst-2019", "berlin-pp"]
    assert all("skipped, missing " + str(tmp_path) in line for line in lines)
    for path in datasets.get("berlin-pp").files():                     # now give berlin-pp its files
        path.parent.mkdir(parents=True, exist_ok=True)
        path.touch()
    lines.clear()
    assert datasets.present(["hk-tst-2019", "berlin-pp"], lines.append) == ["berlin-pp"]
    assert len(lines) == 1 and lines[0].startswith("hk-tst-2019: skipped")
