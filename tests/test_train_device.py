"""Training on a chosen device (``device`` setting) and the training speed benchmark script."""
import sys
from pathlib import Path

import pytest
import torch

from learning.export import load_model
from learning.train import load_config, main, prepare, resolve_device, train

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import train_speed  # noqa: E402

TINY = ["data.datasets=['synthetic']", "data.synthetic.n_epochs=60", "data.synthetic.train_seeds=[1]",
        "data.synthetic.val_seeds=[101]", "data.window=20", "data.stride=10", "train.batch_size=2",
        "train.lr=1e-2", "train.epochs=2", "threads=1"]
no_cuda = not torch.cuda.is_available()


def test_device_names():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    for bad in ("gpu", "cuda:x", "", 0, None):
        with pytest.raises(ValueError, match="device must be 'cpu', 'cuda', 'cuda:N' or 'auto'"):
            resolve_device(bad)
    with pytest.raises(ValueError, match="sees no CUDA GPU" if no_cuda else "only .* CUDA GPU"):
        resolve_device("cuda:99")


@pytest.mark.skipif(not no_cuda, reason="this machine has a CUDA GPU, so 'cuda' is not refused")
def test_asking_for_a_missing_gpu_is_one_line_before_any_data_loads(capsys, tmp_path):
    for setting, expected in (("device=cuda", "sees no CUDA GPU; use device = 'cpu' or 'auto'"),
                              ("device=gpu", "device must be 'cpu', 'cuda', 'cuda:N' or 'auto', got 'gpu'")):
        with pytest.raises(SystemExit) as exit_info:
            main(["--set", setting, "--set", "data.datasets=['nope']", "--out", str(tmp_path / "run")])
        assert exit_info.value.code == 2
        err = capsys.readouterr().err
        assert expected in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "run").exists() or not any((tmp_path / "run").iterdir())


def test_auto_trains_on_the_cpu_here_as_cpu_does(tmp_path):
    """'auto' without a GPU is the CPU run, bit for bit."""
    config = load_config("learning/configs/default.toml", TINY)
    prep = prepare(config)
    cpu = train(config, tmp_path / "cpu", progress=False, prepared=prep, export=False)
    auto = train({**config, "device": "auto"}, tmp_path / "auto", progress=False, prepared=prep, export=False)
    if no_cuda:
        assert [h["val_rmse_3d_m"] for h in auto] == [h["val_rmse_3d_m"] for h in cpu]
    assert prep.train_batch.pr_m.device.type == "cpu"              # the prepared data stay where they were


@pytest.mark.skipif(no_cuda, reason="needs a CUDA GPU (CI has none; run on a GPU machine)")
def test_cuda_run_matches_the_cpu_run_resumes_and_exports(tmp_path, capsys):
    config = load_config("learning/configs/default.toml", TINY)
    prep = prepare(config)
    cpu = train(config, tmp_path / "cpu", progress=False, prepared=prep)
    gpu = train({**config, "device": "cuda"}, tmp_path / "gpu", progress=False, prepared=prep)
    assert "repeats to rounding" in capsys.readouterr().err
    for a, b in zip(cpu, gpu):
        assert abs(a["val_rmse_3d_m"] - b["val_rmse_3d_m"]) < 1e-3
    args = ["--out", str(tmp_path / "gpu"), "--resume", "--set", "train.epochs=3", "--no-progress"]
    assert main(args) == 0
    model = load_model(tmp_path / "gpu" / "model.npz")        # exported to numpy: loads without a GPU
    assert model.metadata["epoch"] in (0, 1, 2, 3)


def test_train_speed_table(tmp_path):
    config = load_config("learning/configs/default.toml", TINY)
    rows = train_speed.time_settings(config, ["cpu"], [1], [2, 4], epochs=2, progress=False)
    assert [(r["device"], r["threads"], r["batch_size"]) for r in rows] == [("cpu", 1, 2), ("cpu", 1, 4)]
    assert rows[0]["speed_up"] == 1.0 and all(r["s_per_epoch"] > 0 and r["windows"] > 0 for r in rows)
    assert rows[1]["speed_up"] == pytest.approx(rows[0]["s_per_epoch"] / rows[1]["s_per_epoch"])
    assert train_speed.max_rmse_difference_m(rows) == 0.0        # one setting per batch size
    assert train_speed.max_rmse_difference_m(rows + [{**rows[0], "val_rmse_3d_m": rows[0]["val_rmse_3d_m"] + 0.5}]) \
        == pytest.approx(0.5)
    with pytest.raises(ValueError, match="--epochs must be at least 2"):
        train_speed.time_settings(config, ["cpu"], [1], [2], epochs=1, progress=False)


def test_train_speed_command_line(tmp_path, capsys):
    out = tmp_path / "speed.md"
    argv = ["--config", "learning/configs/default.toml", "--epochs", "2", "--no-progress", "--out", str(out)]
    assert train_speed.main(argv + [x for s in TINY for x in ("--set", s)]) == 0
    text = out.read_text()
    assert text == capsys.readouterr().out
    assert "| cpu | 1 | 2 |" in text and "CPU cores" in text and "max |dRMSE|" in text
    with pytest.raises(SystemExit) as exit_info:
        train_speed.main(["--device", "tpu"])
    assert exit_info.value.code == 2 and "device must be" in capsys.readouterr().err
