"""Test helper: run RTKLIB ``rnx2rtkp`` with a debug trace and read back what ``satposs`` computed.

With ``-x 4`` (or higher) rnx2rtkp writes ``<outfile>.trace``; for every epoch RTKLIB ``satposs``
(src/ephemeris.c) prints one line per observation:

    4 2019/04/28 12:49:59.925244 sat= 2 rs=  3044925.358  16998886.552  20827006.224 dts= -200123.396 var=  5.760 svh=00

preceded per epoch by ``3 satposs : teph=2019/04/28 12:50:00.003 n=13 ephopt=0`` (the epoch time
stamp, at which ephemerides are chosen). time = signal transmission time (GPST, microseconds), rs = ECEF position [m] at that time (no Sagnac
rotation), dts = satellite clock [ns] with the relativistic term and without TGD/BGD, svh = health.
Rows without ephemeris are printed with zeros and are dropped here.

Checked with Debian's rtklib 2.4.3 b34 (``/usr/bin/rnx2rtkp``), whose satellite numbers are
GPS 1-32, GLONASS 33-59 (R01-R27), Galileo 60-95 (E01-E36), QZSS 96-105 (J01-J10, PRN 193-202),
BeiDou from 106 (C01 = 106); verified against the satellite order of the decoded observations
(``decode_obsdata`` trace lines) of hk-tst-static, which has all five systems.
This build uses Galileo I/NAV records only and ephemerides with toe before the epoch for Galileo,
as lfgnss does (checked on hk-tst-static, whose files carry both I/NAV and F/NAV).
"""
from __future__ import annotations

import re
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lfgnss.time import datetime64_to_gps_s

RNX2RTKP = shutil.which("rnx2rtkp")

_SATPOSS = re.compile(
    r"^4 (\d{4})/(\d\d)/(\d\d) (\d\d):(\d\d):(\d\d\.\d+) sat=\s*(\d+) rs=\s*(\S+)\s+(\S+)\s+(\S+)"
    r" dts=\s*(\S+) var=\s*\S+ svh=([0-9A-Fa-f-]+)")


def rtklib_sat_to_sv(sat: int) -> str:
    """RTKLIB 2.4.3 b34 satellite number -> RINEX 3 id ('G01', 'R05', 'E30', 'J02', 'C01')."""
    if 1 <= sat <= 32:
        return f"G{sat:02d}"
    if sat <= 59:
        return f"R{sat - 32:02d}"
    if sat <= 95:
        return f"E{sat - 59:02d}"
    if sat <= 105:
        return f"J{sat - 95:02d}"
    if sat <= 105 + 63:
        return f"C{sat - 105:02d}"
    raise ValueError(f"RTKLIB satellite number {sat} is outside GPS/GLO/GAL/QZS/BDS")


@dataclass(frozen=True)
class SatposTrace:
    """What RTKLIB ``satposs`` printed, N rows with an ephemeris."""

    sv: np.ndarray           #: (N,) '<U3'
    t_rx_gps_s: np.ndarray   #: (N,) epoch time stamp RTKLIB chose ephemerides at (``teph``, rounded to 1 ms)
    t_tx_gps_s: np.ndarray   #: (N,) transmission time, GPS seconds (rounded to 1 us by the trace)
    pos_ecef_m: np.ndarray   #: (N, 3) (rounded to 1 mm)
    clock_s: np.ndarray      #: (N,) (rounded to 1 ps)
    svh: np.ndarray          #: (N,) int health


def parse_satposs_trace(path: Path) -> SatposTrace:
    """Read the ``satposs`` lines of an rnx2rtkp trace file (see module docstring)."""
    rows, teph = [], []
    current = None
    with open(path, errors="replace") as f:
        for line in f:
            if line.startswith("3 satposs : teph="):
                current = line.split("teph=")[1][:23].replace("/", "-").replace(" ", "T")
            elif " rs=" in line:
                m = _SATPOSS.match(line)
                if m:
                    rows.append(m.groups())
                    teph.append(current)
    stamps = np.array(["{}-{}-{}T{}:{}:{}".format(*r[:6]) for r in rows], dtype="datetime64[ns]")
    pos = np.array([[float(x) for x in r[7:10]] for r in rows]).reshape(-1, 3)
    keep = np.any(pos != 0.0, axis=1)
    return SatposTrace(
        sv=np.array([rtklib_sat_to_sv(int(r[6])) for r in rows], dtype="<U3")[keep],
        t_rx_gps_s=datetime64_to_gps_s(np.array(teph, dtype="datetime64[ns]"))[keep],
        t_tx_gps_s=datetime64_to_gps_s(stamps)[keep],
        pos_ecef_m=pos[keep],
        clock_s=np.array([float(r[10]) * 1e-9 for r in rows])[keep],
        svh=np.array([int(r[11], 16) if r[11] != "-1" else -1 for r in rows], dtype=int)[keep],
    )


def run_satposs(obs: Path, navs: list[Path], workdir: Path, start: str, end: str,
                systems: str = "G,R,E,J,C", interval_s: float | None = None) -> tuple[SatposTrace, list[str]]:
    """Run single-point rnx2rtkp with trace level 4 and return the parsed ``satposs`` lines.

    ``start``/``end`` are 'YYYY/MM/DD HH:MM:SS' (GPST). The command is

        rnx2rtkp -p 0 -x 4 -sys SYSTEMS -ts START -te END [-ti INTERVAL] -o WORKDIR/out.pos OBS NAV...

    Returns the trace and the command line (for messages).
    """
    if RNX2RTKP is None:
        raise FileNotFoundError("rnx2rtkp not on PATH")
    out = Path(workdir) / "out.pos"
    cmd = [RNX2RTKP, "-p", "0", "-x", "4", "-sys", systems,
           "-ts", *start.split(), "-te", *end.split()]
    if interval_s is not None:
        cmd += ["-ti", f"{interval_s:g}"]
    cmd += ["-o", str(out), str(obs), *[str(n) for n in navs]]
    subprocess.run(cmd, check=True, capture_output=True, timeout=120)
    return parse_satposs_trace(Path(str(out) + ".trace")), cmd
