"""Each bundled model file was trained with the configuration its README row names (a config edited without
retraining, or a model copied from another run, shows up here)."""
import re
from dataclasses import replace
from pathlib import Path

import pytest

from estimators.ekf import config_of
from learning.export import load_model
from learning.train import adopt_init, ekf_config, load_config
from lfgnss.paths import model_path

ROOT = Path(__file__).resolve().parents[1]
MODELS = ROOT / "lfgnss" / "data" / "model"
#: How a run was executed, not what it trained: these may differ between the file and today's configuration.
EXECUTION = {"threads", "device"}


def readme_rows() -> dict[str, str]:
    """{model file name: config path} from the model README's table ("made by" may say ``...`` for the module)."""
    rows = {}
    for line in (MODELS / "README.md").read_text().splitlines():
        name = re.match(r"\| `(lfgnss-[\w.-]+\.npz)` \|", line)
        config = re.search(r"--config (learning/configs/[\w.-]+\.toml)", line)
        if name and config:
            rows[name.group(1)] = config.group(1)
    return rows


def same_model_file(a: object, b: object) -> bool:
    """Two ``train.init`` values that name one model file: a path from the repository root, or a bundled name."""
    def where(value: object) -> object:
        return (ROOT / model_path(value)).resolve() if isinstance(value, str) and value else value

    return where(a) == where(b)


def disagreements(stored: dict, expected: dict, path: str = "") -> list[str]:
    """Settings both configurations have whose values differ; a setting newer than the file is not compared, and
    ``train.init`` given as a path in one and a bundled name in the other is the same setting if it is one file."""
    out = []
    for key in stored.keys() & expected.keys() - EXECUTION:
        a, b = stored[key], expected[key]
        if isinstance(a, dict) and isinstance(b, dict):
            out += disagreements(a, b, f"{path}{key}.")
        elif a != b and not (f"{path}{key}" == "train.init" and same_model_file(a, b)):
            out.append(f"{path}{key}: file {a!r}, configuration {b!r}")
    return out


def test_every_bundled_model_file_has_a_readme_row_with_its_command():
    assert sorted(readme_rows()) == sorted(p.name for p in MODELS.glob("*.npz"))


@pytest.mark.parametrize("name, config_path", sorted(readme_rows().items()))
def test_bundled_model_was_trained_with_its_configuration(name, config_path, monkeypatch):
    monkeypatch.chdir(ROOT)     # the README's --config paths are relative to the repository root
    model = load_model(MODELS / name)
    stored = model.metadata["config"]
    expected = adopt_init(load_config(config_path))
    assert disagreements(stored, expected) == [], f"{name} against {config_path}"
    assert stored.get("ekf", {}) == expected["ekf"]
    # the filter the file runs in (estimators.ekf.config_of) is the configuration's, but for the changes its refilter
    # record lists (learning.export --ekf), which its README row names
    changes = {k: new for rec in model.metadata.get("refilter") or [] for k, (_, new) in rec["changes"].items()}
    assert config_of(model) == replace(ekf_config(expected), **changes)
    row = next(line for line in (MODELS / "README.md").read_text().splitlines() if line.startswith(f"| `{name}` |"))
    assert all(f"--ekf {k}=" in row for k in changes), row


def test_a_train_init_path_and_a_bundled_name_compare_equal_only_for_the_same_file():
    """hk-tst-2019 was trained with train.init = the transfer base's path; hk_finetune.toml now names it."""
    stored = load_model(MODELS / "lfgnss-hk-tst-2019.npz").metadata["config"]
    assert stored["train"]["init"] == "lfgnss/data/model/lfgnss-transfer-base.npz"
    assert load_config(ROOT / "learning/configs/hk_finetune.toml")["train"]["init"] == "transfer-base"
    assert disagreements(stored, {"train": {"init": "transfer-base"}}) == []
    assert disagreements(stored, {"train": {"init": str(MODELS / "lfgnss-transfer-base.npz")}}) == []
    assert disagreements(stored, {"train": {"init": "default"}}) == [
        "train.init: file 'lfgnss/data/model/lfgnss-transfer-base.npz', configuration 'default'"]
    assert disagreements({"train": {"init": ""}}, {"train": {"init": "default"}}) != []     # from scratch is not
    assert disagreements({"train": {"epochs": 30}}, {"train": {"epochs": 31}}) != []        # nothing else loosened


def test_bundled_models_are_picked_by_name_everywhere_a_model_file_is(tmp_path, monkeypatch, capsys):
    import estimators
    from learning.export import ModelFileError
    from learning.export import main as export_main
    from lfgnss.paths import bundled_models, model_path

    assert bundled_models() == {p.name.removeprefix("lfgnss-").removesuffix(".npz"): p
                                for p in MODELS.glob("lfgnss-*.npz")}
    assert set(bundled_models()) >= {"default", "hk-tst-2019", "berlin-pp", "hk-tst-static-2020"}
    by_name = load_model("hk-tst-2019")
    assert by_name.metadata == load_model(MODELS / "lfgnss-hk-tst-2019.npz").metadata
    berlin = load_model(MODELS / "lfgnss-berlin-pp.npz")
    assert estimators.create("ekf", noise="berlin-pp").noise.metadata == berlin.metadata
    assert export_main(["--show", "hk-tst-static-2020"]) == 0
    assert "hk-tst-static-2020" in capsys.readouterr().out
    # a file of that name wins over the bundled model; a path with a folder or suffix is never a name
    monkeypatch.chdir(tmp_path)
    (tmp_path / "default").write_text("not a model")
    assert model_path("default") == Path("default")
    with pytest.raises(ModelFileError, match="^default: not an lfgnss model file"):
        load_model("default")
    assert model_path("models/hk-tst-2019") == Path("models/hk-tst-2019")
    assert model_path("hk-tst-2019.npz") == Path("hk-tst-2019.npz")
    with pytest.raises(ModelFileError, match=r"^hk-tst: no such model file or bundled model \(berlin-pp, default, "
                                             r".*\); did you mean 'hk-tst-2019'\?$"):
        load_model("hk-tst")
    with pytest.raises(ModelFileError, match=r"^mine\.npz: no such model file$"):
        load_model("mine.npz")
    # docs/results.md lists the bundled files by file name: that name leads to the model's
    for given in ("lfgnss-default.npz", "lfgnss-default", "elsewhere/lfgnss-default.npz"):
        with pytest.raises(ModelFileError, match=rf"^{given}: no such model file; the bundled lfgnss-default\.npz "
                                                 rf"is named 'default'$"):
            load_model(given)
