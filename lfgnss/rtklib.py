"""Run RTKLIB ``rnx2rtkp`` single-point positioning with the benchmark settings.

The benchmark baseline (``shared/BENCHMARK.md``) is RTKLIB 2.4.3 b34 ``rnx2rtkp`` in single-point
mode: L1, elevation mask 10 deg, broadcast (Klobuchar) ionosphere, Saastamoinen troposphere, the
dataset's constellations. :func:`run_rnx2rtkp` writes those settings to an RTKLIB options file and
runs ``rnx2rtkp -k OPTIONS -o OUT OBS NAV...``. Every option name and enumeration below is one
that rnx2rtkp 2.4.3 b34 itself knows (``strings /usr/bin/rnx2rtkp``: ``pos1-posmode``,
``0:single,...``; ``pos1-navsys`` ``1:gps+2:sbas+4:glo+8:gal+16:qzs+32:bds``); options not
written keep RTKLIB's defaults (no C/N0 mask, ``pos2-rejgdop`` 30, chi-square residual test,
elevation-dependent weights, broadcast ephemeris).

Example::

    from lfgnss.rtklib import run_rnx2rtkp
    pos, seconds = run_rnx2rtkp("rover.obs", ["brdc.nav"], "out.pos", systems=("G", "C"))
    sol = lfgnss.outputs.read_pos(pos)
"""
from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Iterable, Sequence

from .errors import LfgnssError

#: ``pos1-navsys`` bit of each constellation letter (RTKLIB ``SYS_*``).
NAVSYS_BITS = {"G": 1, "S": 2, "R": 4, "E": 8, "J": 16, "C": 32, "I": 64}

#: Benchmark single-point settings, RTKLIB option name -> value (``-k`` file syntax).
BENCHMARK_OPTIONS = {
    "pos1-posmode": "single",
    "pos1-frequency": "l1",
    "pos1-soltype": "forward",
    "pos1-elmask": "10",
    "pos1-snrmask_r": "off",
    "pos1-dynamics": "off",
    "pos1-tidecorr": "off",
    "pos1-ionoopt": "brdc",
    "pos1-tropopt": "saas",
    "pos1-sateph": "brdc",
    "out-solformat": "llh",
    "out-outhead": "on",
    "out-timesys": "gpst",
    "out-timeform": "hms",
    "out-timendec": "3",
    "out-degform": "deg",
    "out-height": "ellipsoidal",
}


class RtklibError(LfgnssError):
    """rnx2rtkp is missing, failed, or wrote no solution file."""


def rnx2rtkp_path() -> str | None:
    """Path of ``rnx2rtkp``: ``$LFGNSS_RNX2RTKP`` if set, else the one on PATH, else None."""
    env = os.environ.get("LFGNSS_RNX2RTKP")
    if env:
        return env if Path(env).is_file() and os.access(env, os.X_OK) else None
    return shutil.which("rnx2rtkp")


def rtklib_available() -> bool:
    """True when an executable ``rnx2rtkp`` can be found."""
    return rnx2rtkp_path() is not None


def navsys_mask(systems: Iterable[str]) -> int:
    """``pos1-navsys`` bit mask of constellation letters (G=1, R=4, E=8, J=16, C=32)."""
    mask = 0
    for s in systems:
        s = str(s).strip().upper()[:1]
        if s not in NAVSYS_BITS:
            raise ValueError(f"unknown constellation {s!r}; use letters of {''.join(NAVSYS_BITS)}")
        mask |= NAVSYS_BITS[s]
    if not mask:
        raise ValueError("no constellation given")
    return mask


def options_text(systems: Iterable[str], elevation_mask_deg: float = 10.0, overrides: dict | None = None) -> str:
    """Contents of an rnx2rtkp ``-k`` options file with the benchmark settings.

    ``overrides`` (RTKLIB option name -> value) replace or add options, e.g. ``{"pos1-snrmask_r": "on"}``.
    """
    opts = dict(BENCHMARK_OPTIONS)
    opts["pos1-elmask"] = f"{float(elevation_mask_deg):g}"
    opts["pos1-navsys"] = str(navsys_mask(systems))
    for key, value in (overrides or {}).items():
        opts[str(key)] = str(value)
    width = max(len(k) for k in opts)
    return "".join(f"{k.ljust(width)} ={v}\n" for k, v in opts.items())


def default_timeout_s(inputs: Iterable[str | Path]) -> float:
    """Wall-clock limit [s] for rnx2rtkp on ``inputs``: 60 s, plus 30 s per MB (about 30 times its usual time)."""
    return 60.0 + 30.0 * sum(Path(p).stat().st_size for p in inputs) / 1e6


def run_rnx2rtkp(obs: str | Path, navs: str | Path | Sequence[str | Path], out_pos: str | Path, *,
                 systems: Iterable[str], elevation_mask_deg: float = 10.0, extra_args: Sequence[str] = (),
                 options: dict | None = None, timeout_s: float | None = None) -> tuple[Path, float]:
    """Single-point positioning of ``obs`` with RTKLIB, benchmark settings; returns (``out_pos``, seconds).

    Parameters
    ----------
    obs : rover RINEX observation file.
    navs : one or several broadcast navigation files.
    out_pos : solution file to write (RTKLIB ``.pos``, GPST calendar time, lat/lon/height).
    systems : constellation letters to use (``pos1-navsys``).
    elevation_mask_deg : ``pos1-elmask``.
    extra_args : more rnx2rtkp arguments, e.g. ``("-ts", "2019/04/28", "12:58:00", "-te", ...)``;
        command-line options take precedence over the options file.
    options : more ``-k`` options (name -> value), e.g. ``{"pos1-snrmask_r": "on"}``.
    timeout_s : wall-clock limit [s]; None: ``default_timeout_s`` of the inputs (rnx2rtkp reads a few MB a second,
        so a hung process is stopped in minutes, not left for ten).

    The seconds returned are the wall time of the rnx2rtkp process alone.

    Raises
    ------
    RtklibError : rnx2rtkp not found, failed, timed out, or wrote no solution file.
    FileNotFoundError : an input file does not exist.
    """
    exe = rnx2rtkp_path()
    if exe is None:
        raise RtklibError("rnx2rtkp not found: install RTKLIB (Debian package 'rtklib') or set $LFGNSS_RNX2RTKP")
    navs = [navs] if isinstance(navs, (str, Path)) else list(navs)
    inputs = [Path(obs), *(Path(n) for n in navs)]
    if not navs:
        raise ValueError("run_rnx2rtkp needs at least one navigation file")
    for p in inputs:
        if not p.is_file():
            raise FileNotFoundError(f"rnx2rtkp input not found: {p}")
    out_pos = Path(out_pos)
    out_pos.parent.mkdir(parents=True, exist_ok=True)
    out_pos.unlink(missing_ok=True)
    text = options_text(systems, elevation_mask_deg, options)
    with tempfile.TemporaryDirectory(prefix="lfgnss-rtklib-") as tmp:
        conf = Path(tmp) / "spp.conf"
        conf.write_text(text)
        cmd = [exe, "-k", str(conf), *map(str, extra_args), "-o", str(out_pos), *map(str, inputs)]
        timeout_s = default_timeout_s(inputs) if timeout_s is None else timeout_s
        t0 = time.perf_counter()
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise RtklibError(f"rnx2rtkp timed out after {timeout_s:g} s: {' '.join(cmd)}") from None
        seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        raise RtklibError(f"rnx2rtkp exited with {proc.returncode}: {' '.join(cmd)}: {' | '.join(tail)}")
    if not out_pos.is_file():
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
        raise RtklibError(f"rnx2rtkp wrote no solution file {out_pos}: {' '.join(cmd)}: {' | '.join(tail)}")
    return out_pos, seconds


def spp_solution(obs, navs, out_pos, *, systems, **kwargs):
    """Run :func:`run_rnx2rtkp` and read its solution (``lfgnss.outputs.read_pos``); returns (Solution, seconds)."""
    from .outputs import read_pos

    path, seconds = run_rnx2rtkp(obs, navs, out_pos, systems=systems, **kwargs)
    return read_pos(path, backend="rtklib"), seconds


__all__ = ["BENCHMARK_OPTIONS", "NAVSYS_BITS", "RtklibError", "navsys_mask", "options_text", "rnx2rtkp_path",
           "rtklib_available", "run_rnx2rtkp", "spp_solution"]
