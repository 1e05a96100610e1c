"""A dataset TOML that is not there: the one-line error lists each place it was looked for."""
from __future__ import annotations

from pathlib import Path

import pytest

from lfgnss import datasets
from lfgnss.errors import InputError


@pytest.fixture
def clean_registry(tmp_path, monkeypatch):
    monkeypatch.setenv("LFGNSS_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(datasets, "_REGISTRY", {})


def test_a_missing_relative_toml_names_where_it_was_looked_for(tmp_path, monkeypatch, clean_registry):
    """Defect: 'gone.toml: unreadable dataset config (No such file or directory)' said not in which folder."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError) as err:
        datasets.register_toml("gone.toml")
    assert str(err.value) == (f"gone.toml: unreadable dataset config (No such file or directory; looked for "
                              f"{tmp_path / 'gone.toml'})")


def test_a_missing_absolute_toml_keeps_its_one_line(tmp_path, clean_registry):
    with pytest.raises(InputError) as err:
        datasets.register_toml(tmp_path / "gone.toml")
    assert str(err.value) == f"{tmp_path / 'gone.toml'}: unreadable dataset config (No such file or directory)"


def test_find_dataset_toml_looks_in_the_given_folders_then_the_current_one(tmp_path, monkeypatch):
    config_dir, work = tmp_path / "configs", tmp_path / "work"
    config_dir.mkdir(), work.mkdir()
    monkeypatch.chdir(work)
    (config_dir / "beside.toml").write_text("")
    (work / "here.toml").write_text("")
    (config_dir / "here.toml").write_text("")
    assert datasets.find_dataset_toml("beside.toml", (config_dir,)) == config_dir / "beside.toml"
    assert datasets.find_dataset_toml("here.toml", (config_dir,)) == config_dir / "here.toml"   # the folder first
    assert datasets.find_dataset_toml("here.toml") == Path("here.toml")                # as given
    with pytest.raises(InputError) as err:
        datasets.find_dataset_toml("sub/gone.toml", (config_dir, "."))
    assert str(err.value) == (f"sub/gone.toml: unreadable dataset config (No such file or directory; looked for "
                              f"{config_dir / 'sub/gone.toml'}, {work / 'sub/gone.toml'})")
    for name in ("a\0b.toml", "x" * 5000):                                   # a NUL, too long a name: not there
        with pytest.raises(InputError, match="No such file or directory; looked for"):
            datasets.find_dataset_toml(name)


def test_a_training_config_naming_a_missing_dataset_toml_lists_both_places(tmp_path, monkeypatch):
    """learning.train's data.register looks beside the configuration, then in the current folder; missing, the error
    comes when the configuration is read, naming both places (before, only the current folder, at data loading)."""
    from learning.train import load_config

    config_dir, work = tmp_path / "configs", tmp_path / "work"
    config_dir.mkdir(), work.mkdir()
    monkeypatch.chdir(work)
    (config_dir / "mine.toml").write_text('[data]\nregister = ["gone.toml"]\n')
    with pytest.raises(InputError) as err:
        load_config(str(config_dir / "mine.toml"), [])
    assert str(err.value) == (f"gone.toml: unreadable dataset config (No such file or directory; looked for "
                              f"{config_dir / 'gone.toml'}, {work / 'gone.toml'})")
    (work / "gone.toml").write_text("")              # found in the current folder: kept as that path
    assert load_config(str(config_dir / "mine.toml"), [])["data"]["register"] == ["gone.toml"]


def test_names_something_is_false_for_names_no_file_system_takes(tmp_path):
    from lfgnss.paths import model_path, names_something

    (tmp_path / "here.toml").write_text("")
    assert names_something(tmp_path / "here.toml")
    assert not names_something(tmp_path / "gone.toml")
    assert not names_something(tmp_path / ("x" * 5000))     # ENAMETOOLONG from the OS
    assert not names_something("a\x00b")                    # ValueError from pathlib
    assert model_path("a\x00b") == Path("a\x00b")           # left for the reader's own one-line error
