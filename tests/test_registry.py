"""The estimator registry: ``create`` refuses options a backend does not take instead of dropping them."""
from __future__ import annotations

import inspect
from pathlib import Path

import numpy as np
import pytest

import estimators
from estimators import base
from estimators.base import backend_options, create
from estimators.ekf import LfgnssEkf, PlainEkf
from estimators.noise import HeuristicNoise, default_noise
from lfgnss.errors import InputError
from lfgnss.paths import default_model_path
from lfgnss.simulate import simulate_sequence


@pytest.mark.parametrize("backend", estimators.available())
def test_every_backend_refuses_a_typo(backend):
    with pytest.raises(TypeError, match=rf"backend '{backend}' has no option 'smoth'"):
        create(backend, smoth=True)


@pytest.mark.parametrize("option", [{"noise": HeuristicNoise()}, {"smooth": True}, {"mode": "fixed-lag"},
                                    {"smoth": True}])
def test_equal_weight_least_squares_takes_no_options(option):
    (name,) = option
    with pytest.raises(TypeError, match=rf"create\('wls'\): backend 'wls' has no option '{name}'.*takes no options"):
        create("wls", **option)


@pytest.mark.parametrize("backend, option, owners", [
    ("wls-weighted", {"smooth": True}, "ekf, plain-ekf"),
    ("wls-weighted", {"mode": "fixed-lag"}, "fgo"),
    ("fgo", {"smooth": True}, "ekf, plain-ekf"),
    ("ekf", {"mode": "batch"}, "fgo"),
    ("plain-ekf", {"use_compensation": True}, "ekf"),
])
def test_an_option_of_another_backend_is_refused_and_its_owners_named(backend, option, owners):
    (name,) = option
    with pytest.raises(TypeError, match=rf"backend '{backend}' has no option '{name}' \(an option of {owners}\)"):
        create(backend, **option)


def test_a_typo_gets_a_suggestion():
    with pytest.raises(TypeError, match=r"'smoth' \(did you mean 'smooth'\?\)"):
        create("ekf", smoth=True)
    with pytest.raises(TypeError, match=r"'smoth' \(did you mean 'smooth', an option of ekf, plain-ekf\?\)"):
        create("wls", smoth=True)


def test_the_options_of_each_backend_are_those_of_its_class():
    assert backend_options("wls") == []
    assert backend_options("wls-weighted") == ["noise"]
    assert backend_options("ekf") == list(inspect.signature(LfgnssEkf).parameters)
    assert backend_options("plain-ekf") == list(inspect.signature(PlainEkf).parameters)
    assert backend_options("fgo") == list(inspect.signature(estimators.LfgnssFgo).parameters)


def test_what_the_command_line_passes_is_accepted():
    """The option sets lfgnss.solve builds for each backend (noise only for ekf and fgo, smoothing for the EKFs)."""
    noise = HeuristicNoise()
    create("wls")
    create("wls-weighted")
    create("plain-ekf", smooth=True, smooth_lag_s=5.0)
    assert create("ekf", noise=noise, smooth=True, smooth_lag_s=5.0).smooth_lag_s == 5.0
    assert create("fgo", noise=noise, mode="fixed-lag").mode == "fixed-lag"


def test_weighted_least_squares_noise_is_checked_and_may_be_a_model_file():
    with pytest.raises(TypeError, match="wls-weighted: noise must be a noise model .* got int"):
        create("wls-weighted", noise=3)
    seq = simulate_sequence(20, seed=9)
    from_file = create("wls-weighted", noise=default_model_path()).solve(seq)
    from_model = create("wls-weighted", noise=default_noise()).solve(seq)
    np.testing.assert_array_equal(from_file.pos_ecef_m, from_model.pos_ecef_m)


@pytest.mark.parametrize("backend, n_epochs", [("ekf", 60), ("fgo", 20)])
def test_noise_may_be_a_model_file_and_anything_else_is_refused_at_construction(backend, n_epochs):
    """``noise`` takes a model file path, as ``--model``; a wrong type fails at construction, not in ``solve``."""
    cls = type(create(backend))
    small = simulate_sequence(n_epochs, seed=9)
    want = create(backend).solve(small).pos_ecef_m
    for path in (str(default_model_path()), Path(default_model_path())):
        est = create(backend, noise=path)
        assert est.noise.metadata == default_noise().metadata
        assert backend != "ekf" or est.config == create("ekf").config     # the filter the file was trained in
        np.testing.assert_array_equal(est.solve(small).pos_ecef_m, want)
        assert cls(noise=path).noise.metadata == default_noise().metadata
    with pytest.raises(InputError, match="my.npz: no such model file"):
        create(backend, noise="my.npz")
    for bad, what in ((3, "int"), (HeuristicNoise, "the class HeuristicNoise")):
        refused = f"noise must be a noise model .* or a model file path, got {what}"
        with pytest.raises(TypeError, match=f"{cls.__name__}: {refused}"):
            create(backend, noise=bad)
        with pytest.raises(TypeError, match=f"{cls.__name__}: {refused}"):
            cls(noise=bad)
        with pytest.raises(TypeError, match=f"PlainEkf: {refused}"):
            PlainEkf(noise=bad)


def test_a_factory_that_takes_any_keyword_checks_them_itself(monkeypatch):
    seen = {}

    def factory(**options):
        seen.update(options)
        return create("wls")

    monkeypatch.setitem(base._REGISTRY, "third-party", factory)
    assert backend_options("third-party") is None
    create("third-party", anything=1)
    assert seen == {"anything": 1}


def test_register_wants_a_name_and_warns_when_it_replaces_a_back_end():
    from estimators.base import _REGISTRY

    class Mine:
        def solve(self, sequence):
            raise NotImplementedError

    with pytest.raises(TypeError, match=r'give the back end\'s name, @register\("name"\), not the Mine itself'):
        estimators.register(Mine)                         # the bare decorator
    with pytest.raises(TypeError, match="not 5"):
        estimators.register(5)
    before = dict(_REGISTRY)
    try:
        estimators.register("mine-36")(Mine)
        with pytest.warns(UserWarning, match="'ekf' now creates .*Mine, replacing the back end of that name"):
            estimators.register("ekf")(Mine)
        with pytest.warns(UserWarning, match="'fgo' now creates"):
            estimators.register("fgo")(Mine)
    finally:
        _REGISTRY.clear()
        _REGISTRY.update(before)
    assert isinstance(estimators.create("ekf"), estimators.LfgnssEkf)
