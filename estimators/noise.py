"""Per-satellite measurement noise: variance R [m^2] and innovation compensation v^c [m].

A noise model is any callable ``model(sequence) -> (r_m2, vc_m)`` returning two (T, N) arrays.
Padded/masked slots may hold any finite value; estimators ignore them.
"""
from __future__ import annotations

import numbers
import os
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from functools import lru_cache
from typing import Protocol, runtime_checkable

import numpy as np

from lfgnss import weighted_fix
from lfgnss.corrections import geometric_range_m
from lfgnss.features import system_median_m
from lfgnss.paths import default_model_path
from lfgnss.sequence import Sequence

from .base import caller_stacklevel, usable_measurements


@runtime_checkable
class NoiseModel(Protocol):
    """Maps a Sequence to pseudorange variances R (T, N) [m^2] and compensations v^c (T, N) [m].

    A learned model also carries the filter it was trained in (``metadata["ekf_config"]``, ``estimators.config_of``),
    which the EKF runs when given no ``config``; a function wrapping one (scaling its R, say) carries none: pass
    ``config=estimators.config_of(model)`` to keep the model's filter.
    """

    def __call__(self, sequence: Sequence) -> tuple[np.ndarray, np.ndarray]:
        ...


@lru_cache(maxsize=1)
def default_noise() -> NoiseModel:
    """The bundled LF-GNSS model (``lfgnss.paths.default_model_path``), read once: what ``create("ekf")`` uses."""
    from learning.export import load_model

    return load_model(default_model_path())


def carries_filter(noise: object) -> bool:
    """Whether ``noise`` says which filter it belongs to: a learned model (its file's metadata), or a hand-set one."""
    return isinstance(noise, (HeuristicNoise, FixedNoise, TruthNoise)) or isinstance(getattr(noise, "metadata", None),
                                                                                       dict)


def warn_no_filter_settings(noise: object, owner: str, uses: str, keep: str) -> None:
    """Warn, unless ``noise`` ``carries_filter``, that ``owner`` takes the default EkfConfig's settings (``uses``
    says which and how) for it, and how a wrapped learned model keeps its own (``keep``)."""
    if not carries_filter(noise):
        warnings.warn(f"{owner}: the noise model {describe_noise(noise)} carries no filter settings of its own "
                      f"(it is not a learned model file), so {uses}; a wrapped learned model keeps its own with "
                      f"{keep}", stacklevel=caller_stacklevel())


def describe_noise(noise: object) -> str:
    """A noise model in a few words for reprs: its file for a learned model, its name for a function, else its repr."""
    path = getattr(noise, "path", None)
    if isinstance(path, (str, os.PathLike)):
        return f"{type(noise).__name__}({os.fspath(path)!r})"
    if isinstance(noise, (HeuristicNoise, FixedNoise, TruthNoise)):
        return repr(noise)
    name = getattr(noise, "__qualname__", None)
    if isinstance(name, str):
        return f"<function {name}>"
    if type(noise).__repr__ is object.__repr__:
        return f"<{type(noise).__qualname__}>"
    text = repr(noise)
    return text if len(text) <= 120 else text[:117] + "..."


def resolve_noise(noise: object, owner: str) -> NoiseModel | None:
    """``noise`` as a NoiseModel: a model file path (str or Path, ``~`` expanded) or a bundled model's name is read
    as ``--model`` is; None stays None."""
    if noise is None:
        return None
    if isinstance(noise, (str, os.PathLike)):
        from learning.export import load_model   # numpy only, as default_noise; raises ModelFileError naming the file

        return load_model(os.path.expanduser(noise))
    what = not_a_model(noise)
    if what:
        raise TypeError(f"{owner}: noise must be a noise model (sequence -> (r_m2, vc_m)) or a model file path, "
                        f"got {what}")
    return noise


def not_a_model(value: object) -> str | None:
    """What ``value`` is, in words, when it cannot be a noise model (a class, or something not callable); else None."""
    if isinstance(value, type):
        return f"the class {value.__name__} (pass an instance)"
    return None if callable(value) else type(value).__name__


def _must_return(owner: str, noise: object) -> str:
    """``"<owner>: the noise model <it> must return (r_m2, vc_m), ..."``, the start of every message on its output."""
    which = "a noise model" if noise is None else f"the noise model {describe_noise(noise)}"
    return f"{owner}: {which} must return (r_m2, vc_m), each a (T, N) float array [m^2, m]"


def noise_output(owner: str, out: object, noise: object = None) -> tuple[object, object]:
    """A noise model's return value as its two parts ``(r_m2, vc_m)``; TypeError naming ``owner`` and ``noise`` (the
    model, for its description) otherwise."""
    if isinstance(out, Mapping):
        keys = ", ".join(repr(k) for k in list(out)[:4])
        raise TypeError(f"{_must_return(owner, noise)}; got a {type(out).__name__} (keys {keys}): return the tuple")
    try:
        if len(out) == 2:
            return out[0], out[1]
    except (TypeError, KeyError, IndexError):
        pass
    got = (f"{len(out)} values" if isinstance(out, (tuple, list))
           else f"an array of shape {out.shape}" if isinstance(out, np.ndarray) else type(out).__name__)
    raise TypeError(f"{_must_return(owner, noise)}; got {got}")


def _value_text(value: object) -> str:
    """What a noise model gave where a float array belongs, in a few words (``float_array``'s messages)."""
    if type(value).__module__.split(".")[0] == "torch":
        grad = " that requires grad" if getattr(value, "requires_grad", False) else ""
        return f"a torch tensor{grad} (return tensor.detach().cpu().numpy())"
    dtype = getattr(value, "dtype", None)
    if dtype is not None:
        return f"an array of dtype {dtype}"
    return f"a {type(value).__name__} that does not convert to float"


def _as_float(value: object) -> np.ndarray | None:
    """``value`` as a float array, None where it does not convert (strings, a torch tensor that requires grad)."""
    try:
        return np.asarray(value, float)
    except (TypeError, ValueError, RuntimeError):
        return None


def float_array(owner: str, key: str, value: object, noise: object = None) -> np.ndarray:
    """``value`` (a noise model's ``key``, r_m2 or vc_m) as a float array; TypeError naming ``owner`` and ``noise``
    when it does not convert (``_as_float``)."""
    out = _as_float(value)
    if out is None:
        raise TypeError(f"{_must_return(owner, noise)}; its {key} is {_value_text(value)}")
    return out


#: Pseudorange variance [m^2] above which a noise model switches a satellite off (sigma 1000 km, beyond any
#: pseudorange error): ``switched_on`` treats the slot as masked out, pseudorange and Doppler (``checked_noise``).
R_OFF_M2 = 1e12


def switched_on(usable: np.ndarray, r_m2: np.ndarray) -> np.ndarray:
    """(T, N) bool: ``usable`` slots whose R [m^2] is at most ``R_OFF_M2``; the others are switched off.

    Dropping a pseudorange of variance r [m^2] moves an estimate by about (posterior variance / r) times its
    innovation: above ``R_OFF_M2``, a micrometre for a 1000 km innovation at a posterior variance of 1 m^2. Keeping it
    makes the innovation covariance ``S = H P H^T + R`` singular to machine precision (rcond ~ min(r) / max(r):
    scipy's LinAlgWarning at every update).
    """
    return usable & (r_m2 <= R_OFF_M2)


class NoiseWarning(UserWarning):
    """An estimator's warning about its noise model's R: every usable pseudorange of an epoch switched off, or R
    looking given in another unit (``warn_noise``). Its own category, so that a noise model that runs an estimator
    to make its R (an online model file given to the factor graph) can leave the judging to the estimator it serves."""


def warn_switched_off(owner: str, sequence_name: str, usable: np.ndarray, on: np.ndarray) -> None:
    """Warn when the noise model switched off (``switched_on``) every usable pseudorange of an epoch: ``usable`` and
    ``on`` (T, N) before and after. Such an epoch has nothing to place a position; a filter only coasts through it."""
    emptied = np.asarray(usable, bool).any(axis=-1) & ~np.asarray(on, bool).any(axis=-1)
    if emptied.any():
        warnings.warn(f"{owner}: the noise model switched off every usable pseudorange (R above "
                      f"estimators.noise.R_OFF_M2, {R_OFF_M2:.0e} m^2) at {int(emptied.sum())} of {emptied.size} "
                      f"epochs of {sequence_name!r} (first at epoch {int(np.flatnonzero(emptied)[0])}): no satellite "
                      f"places a position there", NoiseWarning, stacklevel=caller_stacklevel())


#: Range of the median ratio of a noise model's R to the hand-set C/N0-elevation variance (``HeuristicNoise``'s) on
#: the same pseudoranges outside which ``warn_implausible_r`` says R looks given in another unit. The bundled models
#: and TruthNoise lie at 0.04-5.3 on the benchmark splits; R in cm^2 is 1e4 times, in km^2 1e-6 times its m^2 value.
R_RATIO_PLAUSIBLE = (1e-4, 1e2)


def warn_implausible_r(owner: str, sequence: Sequence, on: np.ndarray, r_m2: np.ndarray) -> None:
    """Warn once when the median of R [m^2] over the hand-set C/N0-elevation variance, on the switched-on usable
    slots ``on`` of ``sequence``, lies outside ``R_RATIO_PLAUSIBLE``: a variance in cm^2 or km^2 runs without
    error, but weighs the pseudoranges otherwise than meant. Judged against the signals' own strength, so
    weak-signal data does not trip it."""
    r_m2 = np.asarray(r_m2, float)
    on = np.asarray(on, bool) & np.isfinite(sequence.cn0_dbhz) & np.isfinite(sequence.el_rad)
    if not on.any():
        return
    ratio = float(np.median(r_m2[on] / weighted_fix.cn0_elevation_variance_m2(sequence.cn0_dbhz[on],
                                                                                  sequence.el_rad[on])))
    low, high = R_RATIO_PLAUSIBLE
    if not low <= ratio <= high:
        median = float(np.median(r_m2[on]))
        warnings.warn(f"{owner}: the noise model's R over the usable pseudoranges of {sequence.name!r} is a median "
                      f"{ratio:.3g} times the hand-set C/N0-elevation variance (median R {median:.3g} m^2, sd "
                      f"{np.sqrt(median):.3g} m), outside {low:g}-{high:g}: R is a variance in m^2 (the sd "
                      "squared); is it in another unit?", NoiseWarning, stacklevel=caller_stacklevel())


def warn_noise(owner: str, sequence: Sequence, usable: np.ndarray, on: np.ndarray, r_m2: np.ndarray) -> None:
    """A run's warnings on its noise model's R [m^2]: ``usable`` and ``on`` (T, N) the slots before and after it
    switched some off (``switched_on``): ``warn_implausible_r``, then ``warn_switched_off``."""
    warn_implausible_r(owner, sequence, on, r_m2)
    warn_switched_off(owner, sequence.name, usable, on)


def switched_on_warned(owner: str, sequence: Sequence, usable: np.ndarray, r_m2: np.ndarray) -> np.ndarray:
    """``switched_on(usable, r_m2)``, with the run's warnings on R (``warn_noise``): R in another unit, an epoch left
    no usable pseudorange."""
    on = switched_on(usable, r_m2)
    warn_noise(owner, sequence, usable, on, r_m2)
    return on


def checked_noise(owner: str, sequence_name: str, usable: np.ndarray, r_m2: object, vc_m: object,
                  noise: object = None) -> tuple[np.ndarray, np.ndarray]:
    """A noise model's ``(r_m2, vc_m)`` as float arrays shaped like ``usable``; ValueError naming the first bad epoch.

    R must be > 0 [m^2] and v^c finite [m] on the usable slots; other slots may hold anything. An R above
    ``R_OFF_M2`` (1e30 or inf, say) switches the satellite off (``switched_on``): the estimators leave it out as if
    masked, whatever its v^c.
    Values that are not numbers are a TypeError naming ``owner`` and the model ``noise`` (``float_array``). Whether
    R's scale is plausible is ``warn_implausible_r``'s, which the estimators call once per run (``warn_noise``).
    """
    r = float_array(owner, "r_m2", r_m2, noise)
    vc = float_array(owner, "vc_m", vc_m, noise)
    if r.shape != usable.shape or vc.shape != usable.shape:
        raise ValueError(f"{owner}: noise model gave shapes {r.shape}, {vc.shape} for sequence {sequence_name!r}, "
                         f"expected {usable.shape}")
    # +inf is above R_OFF_M2 like 1e30: the natural way to say "off"; v^c of a slot switched off is never used
    off = r > R_OFF_M2
    for what, bad in (("non-positive or NaN R (an R above R_OFF_M2 = 1e12 m^2, inf too, switches a satellite off)",
                       ~(r > 0)), ("non-finite v^c", ~np.isfinite(vc) & ~off)):
        bad &= usable
        if bad.any():
            where = f" (first at epoch {int(np.argwhere(bad)[0, 0])})" if bad.ndim == 2 else ""
            raise ValueError(f"{owner}: noise model gave {what} on usable satellites of {sequence_name!r}{where}")
    return r, vc


#: Below this C/N0 [dB-Hz] on a usable slot the hand-set noise model warns: a real signal is not that weak (the front
#: end masks below 20), and its R (1e9 m^2 at 0 dB-Hz) shuts the satellite out without a word.
FAINT_CN0_DBHZ = 10.0


@dataclass(frozen=True)
class HeuristicNoise:
    """Hand-set noise from C/N0 and elevation, no compensation (the "plain EKF" baseline).

    r = (floor_m^2 + cn0_scale_m2 * 10^(-C/N0 / 5)) / sin(max(el, el_min))^elevation_power

    Defaults chosen on the validation splits of hk-tst-2019, berlin-pp and hk-tst-static-2020 (grid over
    floor 2/5 m, scale 9e7/1e9/1e10, elevation power 1/2; EKF 3D RMSE 10.5 / 14.1 / 3.8 m there):
    sigma is 2.2 m at 45 dB-Hz, 3.7 m at 40, 10 m at 35 and 32 m at 30 dB-Hz at zenith (``lfgnss.weighted_fix``).
    """

    floor_m: float = weighted_fix.FLOOR_M
    cn0_scale_m2: float = weighted_fix.CN0_SCALE_M2
    elevation_power: float = weighted_fix.ELEVATION_POWER
    el_min_rad: float = weighted_fix.EL_MIN_RAD

    def __post_init__(self) -> None:
        for name in ("floor_m", "cn0_scale_m2", "elevation_power", "el_min_rad"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not np.isfinite(value) or value < 0:
                raise ValueError(f"HeuristicNoise.{name} must be a finite number >= 0, got {value!r}")
        if not self.floor_m > 0 and not self.cn0_scale_m2 > 0:
            raise ValueError("HeuristicNoise needs floor_m > 0 or cn0_scale_m2 > 0 (else R = 0)")
        if not 0 < self.el_min_rad <= np.pi / 2:
            raise ValueError(f"HeuristicNoise.el_min_rad must be in (0, pi/2] [rad], "
                             f"got {self.el_min_rad!r}")

    def __call__(self, sequence: Sequence) -> tuple[np.ndarray, np.ndarray]:
        """(r_m2, vc_m), each (T, N): R [m^2] from C/N0 and elevation [rad], v^c = 0 [m]; slots no estimator can use
        (``usable_measurements``: no pseudorange, say) get the zenith R of 45 dB-Hz."""
        used = usable_measurements(sequence)
        bad = used & ~(np.isfinite(sequence.cn0_dbhz) & np.isfinite(sequence.el_rad))
        if bad.any():
            raise ValueError(f"HeuristicNoise: C/N0 or elevation is not finite on a usable satellite of "
                             f"{sequence.name!r} (first at epoch {int(np.argwhere(bad)[0, 0])})")
        steep = used & (np.abs(np.asarray(sequence.el_rad, float)) > np.pi / 2 + 1e-9)
        if steep.any():
            k, i = np.argwhere(steep)[0]
            raise ValueError(f"HeuristicNoise: elevation {float(sequence.el_rad[k, i]):g} beyond pi/2 on a usable "
                             f"satellite of {sequence.name!r} (epoch {int(k)}): Sequence.el_rad is in radians, "
                             f"not degrees")
        faint = used & (np.asarray(sequence.cn0_dbhz, float) < FAINT_CN0_DBHZ)
        if faint.any():
            warnings.warn(f"HeuristicNoise: C/N0 below {FAINT_CN0_DBHZ:g} dB-Hz on {int(faint.sum())} usable "
                          f"slot(s) of {sequence.name!r} (first at epoch {int(np.argwhere(faint)[0, 0])}): their R is "
                          f"astronomical, so they hardly count; a C/N0 of 0 for 'unknown'? (lfgnss's quality control "
                          f"masks C/N0 below 20 dB-Hz)", stacklevel=caller_stacklevel())
        cn0 = np.where(used, sequence.cn0_dbhz, 45.0)
        el = np.where(used, sequence.el_rad, np.pi / 2)
        r = weighted_fix.cn0_elevation_variance_m2(cn0, el, floor_m=self.floor_m, cn0_scale_m2=self.cn0_scale_m2,
                                                    elevation_power=self.elevation_power, el_min_rad=self.el_min_rad)
        return r, np.zeros_like(r)


@dataclass(frozen=True, eq=False, repr=False)
class FixedNoise:
    """Precomputed ``(r_m2, vc_m)`` arrays (T, N), e.g. from an offline network run or a test.

    Calling it checks that the arrays fit the sequence and returns them unchanged. ``==`` is identity (arrays).
    """

    r_m2: np.ndarray
    vc_m: np.ndarray

    def __post_init__(self) -> None:
        """TypeError naming FixedNoise and the array whose values are not numbers (as ``float_array``)."""
        for key, unit in (("r_m2", "m^2"), ("vc_m", "m")):
            if _as_float(getattr(self, key)) is None:
                raise TypeError(f"FixedNoise: {key} must be a (T, N) float array [{unit}], "
                                f"got {_value_text(getattr(self, key))}")

    def __repr__(self) -> str:
        """The arrays' shapes, not their values: ``FixedNoise(r_m2 (T, N), vc_m (T, N))``."""
        return f"FixedNoise(r_m2 {np.shape(self.r_m2)}, vc_m {np.shape(self.vc_m)})"

    def __call__(self, sequence: Sequence) -> tuple[np.ndarray, np.ndarray]:
        """The stored (r_m2, vc_m) [m^2, m], after checking they are shaped like ``sequence``'s (T, N) slots."""
        shape = sequence.mask.shape
        if np.shape(self.r_m2) != shape or np.shape(self.vc_m) != shape:
            raise ValueError(f"FixedNoise: arrays {np.shape(self.r_m2)}, {np.shape(self.vc_m)} "
                             f"do not fit sequence {sequence.name!r} of shape {shape}")
        return np.asarray(self.r_m2, float), np.asarray(self.vc_m, float)


def constellation_residual_m(sequence: Sequence, pos_ecef_m: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """(T, N) ``pr - range`` at ``pos_ecef_m`` (T, 3) [m] minus each epoch's median per constellation (its receiver
    clock and ISB) over the ``ok`` slots [m]; NaN outside ``ok``."""
    pos = np.nan_to_num(np.asarray(pos_ecef_m, float))
    raw = np.where(ok, sequence.pr_m - geometric_range_m(sequence.sat_pos_ecef_m, pos[:, None, :]), np.nan)
    return raw - system_median_m(raw, ok, sequence.system_index, len(sequence.systems))


@dataclass(frozen=True)
class TruthNoise:
    """R from the ground truth: a reference to judge noise models by, not a method (it reads the truth).

    r = e^2 + floor_m^2 [m^2], where e [m] is each pseudorange's error at the true position once the epoch's
    median per constellation (its receiver clock and ISB) is removed: the weights of shared/BENCHMARK.md's
    "weights taken from the truth" row. No v^c. Epochs without truth take ``fallback``'s R.
    """

    floor_m: float = 1.0
    fallback: HeuristicNoise = HeuristicNoise()

    def __post_init__(self) -> None:
        if (isinstance(self.floor_m, bool) or not isinstance(self.floor_m, numbers.Real)
                or not 0 < self.floor_m < np.inf):
            raise ValueError(f"TruthNoise.floor_m must be a finite number > 0 [m], got {self.floor_m!r}")
        what = not_a_model(self.fallback)
        if what:
            raise TypeError(f"TruthNoise: fallback must be a noise model (sequence -> (r_m2, vc_m)), got {what}")

    def __call__(self, sequence: Sequence) -> tuple[np.ndarray, np.ndarray]:
        """(r_m2, vc_m), each (T, N): R [m^2] from the true pseudorange errors, v^c = 0 [m]."""
        labelled = np.all(np.isfinite(sequence.truth_ecef_m), axis=-1)
        if len(labelled) and not labelled.any():
            warnings.warn(f"TruthNoise: sequence {sequence.name!r} has no ground truth (build_sequence(..., "
                          f"truth_ecef_m=...)); every epoch takes the fallback's R, a plain EKF",
                          stacklevel=caller_stacklevel())
        ok = sequence.mask & labelled[:, None]
        error = constellation_residual_m(sequence, sequence.truth_ecef_m, ok)
        owner = "TruthNoise.fallback"
        r_fallback = float_array(owner, "r_m2", noise_output(owner, self.fallback(sequence), self.fallback)[0],
                                 self.fallback)
        if r_fallback.shape != ok.shape:
            raise ValueError(f"TruthNoise: its fallback {describe_noise(self.fallback)} gave R of shape "
                             f"{r_fallback.shape} for sequence {sequence.name!r}, expected {ok.shape}")
        r = np.where(ok, np.nan_to_num(error) ** 2 + self.floor_m ** 2, r_fallback)
        return r, np.zeros_like(r)
