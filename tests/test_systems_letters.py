"""Unknown constellation letters: one check (``lfgnss.constants.unknown_systems``) for ``lfgnss.load``, dataset
TOML files and ``--systems``, each naming the same letters in the order given and the valid ones."""
from __future__ import annotations

import argparse

import pytest

import lfgnss
from lfgnss import datasets
from lfgnss.constants import unknown_systems
from lfgnss.errors import InputError
from lfgnss.solve import _systems


@pytest.mark.parametrize("letters, unknown", [
    ("GCERJ", ""), ("gcerj", ""), ("", ""), (["G", "r"], ""),
    ("gxQxq", "XQ"),                      # upper case, each once, in the order given
    (["x", "G", "q", "X"], "XQ"),
    (";G,", ";,"),                        # any character that is no letter of SYSTEMS
])
def test_unknown_systems_are_upper_case_each_once_in_the_order_given(letters, unknown):
    assert unknown_systems(letters) == unknown


def test_load_refuses_unknown_systems_before_reading_any_file(tmp_path):
    """Defect: the letters were checked after the files were read (a missing file hid them), in sorted order."""
    with pytest.raises(ValueError) as err:
        lfgnss.load(tmp_path / "missing.obs", tmp_path / "missing.nav", systems="GxQx")
    assert str(err.value) == "unknown constellation letter(s) XQ in the requested systems; use GCERJ"


def test_load_still_takes_systems_as_a_generator(tmp_path):
    """The letters are read once (a generator is not exhausted by the check)."""
    with pytest.raises(ValueError, match=r"letter\(s\) X in"):
        lfgnss.load(tmp_path / "missing.obs", tmp_path / "missing.nav", systems=(c for c in "GX"))


def test_the_three_checks_name_the_same_letters(tmp_path, sample_toml, monkeypatch):
    """Defect: lfgnss.load and a dataset TOML sorted the unknown letters (QX), --systems kept their order (XQ)."""
    monkeypatch.setattr(datasets, "_REGISTRY", {})
    toml = sample_toml("letters")
    toml.write_text(toml.read_text().replace('systems = ["G", "R"]', 'systems = ["x", "G", "q", "X"]'))
    with pytest.raises(InputError) as from_toml:
        datasets.register_toml(toml)
    with pytest.raises(ValueError) as from_load:
        lfgnss.load(tmp_path / "missing.obs", tmp_path / "missing.nav", systems=["x", "G", "q", "X"])
    with pytest.raises(argparse.ArgumentTypeError) as from_option:
        _systems("x G q X")
    assert str(from_toml.value) == f"{toml}: unknown constellation letter(s) XQ in systems; use GCERJ"
    assert "letter(s) XQ in the requested systems; use GCERJ" in str(from_load.value)
    assert "letter(s) 'XQ' in 'x G q X'; use letters of GCERJ" in str(from_option.value)
