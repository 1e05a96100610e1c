"""Broadcast navigation messages: RINEX 2/3 navigation files -> frozen records of numpy arrays.

georinex reads the files (plain, ``.gz``; RINEX 2 GPS ``.n``, RINEX 2 GLONASS ``.g``, RINEX 3 per
constellation and mixed); everything is converted here, at the boundary, into
:class:`KeplerEphemerides` (GPS, Galileo, QZSS, BeiDou), :class:`GlonassEphemerides` and the
Klobuchar coefficients of the headers, all bundled in :class:`Navigation`.

Times are GPS seconds since 1980-01-06 (``lfgnss.time``) whatever the scale written in the file:
BeiDou epochs/toe are BDT (GPST = BDT + 14 s), Galileo weeks are GST weeks aligned with GPS weeks,
GLONASS epochs are UTC (GPST = UTC + leap seconds), as RTKLIB ``decode_eph``/``decode_geph`` do.
"""
from __future__ import annotations

import datetime as dt
import hashlib
import io
import pickle
import re
import warnings
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Iterable

import numpy as np

from .errors import RinexError
from .paths import cache_file, load_cached, store_cached
from .rinex import RinexWarning, _decode
from .time import BDT_MINUS_GPST_S, SECONDS_PER_WEEK, datetime64_to_gps_s, utc_to_gps_s

if TYPE_CHECKING:
    import pandas as pd

KEPLER_SYSTEMS = ("G", "E", "J", "C")

# georinex variable name of the fields that differ between systems
_IODE_NAME = {"G": "IODE", "J": "IODE", "E": "IODnav", "C": "AODE"}
_HEALTH_NAME = {"G": "health", "J": "health", "E": "health", "C": "SatH1"}
# Galileo data source bits (RINEX 3 "Data sources"): 0 I/NAV E1-B, 1 F/NAV E5a-I, 2 I/NAV E5b-I
_GAL_INAV_BITS = 0b101
_GAL_FNAV_BIT = 0b010


@dataclass(frozen=True, eq=False)
class KeplerEphemerides:
    """Keplerian broadcast ephemerides (GPS, Galileo, QZSS, BeiDou), one row per record, K rows.

    Sorted by (sv, toe, ttr). Angles in rad, angle rates in rad/s; ``toe``/``toc``/``ttr`` in GPS
    seconds since 1980-01-06 (BeiDou BDT already shifted by +14 s). ``tgd_s`` is the group delay of
    the single-frequency code the clock must be corrected for: GPS/QZSS TGD (L1 C/A), BeiDou TGD1
    (B1I), Galileo BGD(E1, E5b) for I/NAV records (BGD(E1, E5a) for a satellite that only has F/NAV).
    """

    sv: np.ndarray              #: (K,) '<U3', e.g. 'G05'
    system: np.ndarray          #: (K,) '<U1', 'G' | 'E' | 'J' | 'C'
    toe_gps_s: np.ndarray       #: (K,) time of ephemeris
    toc_gps_s: np.ndarray       #: (K,) time of clock
    ttr_gps_s: np.ndarray       #: (K,) transmission time of the message (NaN if absent)
    sqrt_a_sqrt_m: np.ndarray   #: (K,) square root of the semi-major axis [m^0.5]
    e: np.ndarray               #: (K,) eccentricity [-]
    i0_rad: np.ndarray
    omega0_rad: np.ndarray      #: longitude of ascending node at weekly epoch
    omega_rad: np.ndarray       #: argument of perigee
    m0_rad: np.ndarray
    delta_n_rad_s: np.ndarray
    omega_dot_rad_s: np.ndarray
    idot_rad_s: np.ndarray
    cuc_rad: np.ndarray
    cus_rad: np.ndarray
    crc_m: np.ndarray
    crs_m: np.ndarray
    cic_rad: np.ndarray
    cis_rad: np.ndarray
    af0_s: np.ndarray
    af1_s_s: np.ndarray
    af2_s_s2: np.ndarray
    tgd_s: np.ndarray
    health: np.ndarray          #: (K,) int, 0 = healthy
    iode: np.ndarray            #: (K,) int (Galileo IODnav, BeiDou AODE)
    accuracy_m: np.ndarray      #: (K,) URA (GPS, QZSS, BeiDou) or SISA (Galileo; -1: no prediction) [m]; 0 if absent

    def __len__(self) -> int:
        return len(self.sv)


@dataclass(frozen=True, eq=False)
class GlonassEphemerides:
    """GLONASS broadcast ephemerides, one row per record, K rows, sorted by (sv, toe, tof).

    State at ``toe`` in PZ-90 ECEF. Clock: dts(t) = -tau_n + gamma_n (t - toe) (RINEX stores -tau_n).
    """

    sv: np.ndarray              #: (K,) '<U3', e.g. 'R07'
    toe_gps_s: np.ndarray       #: (K,) epoch of the ephemeris (UTC in the file) as GPS seconds
    tof_s: np.ndarray           #: (K,) message frame time as written (s of UTC day/week; NaN if absent), tie-break only
    pos_ecef_m: np.ndarray      #: (K, 3)
    vel_ecef_m_s: np.ndarray    #: (K, 3)
    acc_ecef_m_s2: np.ndarray   #: (K, 3) luni-solar acceleration
    tau_n_s: np.ndarray         #: (K,) clock offset, ICD sign (satellite time minus GLONASS time is -tau_n)
    gamma_n: np.ndarray         #: (K,) relative frequency offset [-]
    k: np.ndarray               #: (K,) int frequency channel number
    health: np.ndarray          #: (K,) int, 0 = healthy

    def __len__(self) -> int:
        return len(self.sv)


@dataclass(frozen=True, eq=False)
class Navigation:
    """Everything :func:`load_nav` read: ephemerides, Klobuchar coefficients and the file names.

    ``iono`` maps 'GPS' and/or 'BDS' to 8 Klobuchar coefficients (alpha0..3 [s, s/sc, s/sc^2, s/sc^3],
    beta0..3 [s, ...]) when a header had them (RINEX 2 ION ALPHA/BETA, RINEX 3 GPSA/GPSB, BDSA/BDSB).
    ``warnings`` holds one ``PATH:LINE: reason`` note per damaged record (or lines) that was skipped.
    """

    kepler: KeplerEphemerides
    glonass: GlonassEphemerides
    iono: dict[str, np.ndarray]
    sources: tuple[str, ...]
    warnings: tuple[str, ...] = ()


_CACHE_VERSION = 8       # 8: 3.05 files with 4-line GLONASS records; 7: RINEX 2 records in 3.0x files, damaged
#                          QZSS L6-flagged records; 6: GLONASS epochs on the 15 min grid, blank trailing fields;
#                          5: accuracy_m, GLONASS channels past 128


def load_nav(paths: str | Path | Iterable[str | Path], *, cache: bool = True) -> Navigation:
    """Read one or several RINEX navigation files into a :class:`Navigation`.

    Parameters
    ----------
    paths : path or iterable of paths
        RINEX 2 (``.n``, ``.g``) or RINEX 3 (single-system or mixed) navigation files, optionally
        gzip-compressed. Records from several files are concatenated; exact duplicates are dropped.
    cache : bool
        Reuse/write the parsed result in ``lfgnss.paths.cache_dir()``, keyed by the files' content.

    Warns
    -----
    RinexWarning
        Once per file with damaged records (an unreadable value, non-ASCII bytes, a wrong number of
        lines, an impossible epoch): those records are skipped, every other one is kept. The notes,
        ``PATH:LINE: reason``, are in ``Navigation.warnings``. Also once per file of several that is a RINEX
        file of another kind (meteorological, observation: a glob over a station's folder), left out.

    Raises
    ------
    RinexError
        A file is missing, empty, unreadable, not a navigation file or has no GPS/Galileo/QZSS/
        BeiDou/GLONASS record (or none that is readable): one line ``PATH[:LINE]: reason``.
    """
    if isinstance(paths, (str, Path)):
        paths = [paths]
    paths = [Path(p) for p in paths]
    if not paths:
        raise ValueError("load_nav needs at least one file")
    nav = _load_cached(paths) if cache else _parse_nav(paths)
    for source in dict.fromkeys(nav.sources):  # also on a cache hit: the same file always gives the same warning
        notes = [w for w in nav.warnings if w.startswith(source + ":")]
        if notes and notes[0].endswith(LEFT_OUT):
            warnings.warn(notes[0], RinexWarning, stacklevel=2)
        elif notes:
            warnings.warn(f"{source}: {len(notes)} problem(s), damaged navigation records skipped; first: {notes[0]}",
                          RinexWarning, stacklevel=2)
    return nav


#: Why a file among several navigation files is left out, and the note saying so.
NOT_NAVIGATION = "not a RINEX 2/3 navigation file"
NO_SUPPORTED = "no GPS/Galileo/QZSS/BeiDou/GLONASS ephemeris records"
LEFT_OUT = "left out of the navigation files"


def _load_cached(paths: list[Path]) -> Navigation:
    """:func:`_parse_nav` through the cache, keyed by the files' content."""
    digest = hashlib.sha256(str(_CACHE_VERSION).encode())
    for path in paths:
        try:
            digest.update(path.read_bytes())
        except OSError:
            return _parse_nav(paths)  # the parser reports the unreadable file
    target = cache_file("nav", f"{digest.hexdigest()[:24]}.pkl")
    cached = load_cached(target, lambda entry: pickle.loads(entry.read_bytes()))
    if cached is not None:
        sources = tuple(str(p) for p in paths)
        return Navigation(cached.kepler, cached.glonass, cached.iono, sources,
                          _rename(cached.warnings, cached.sources, sources))
    nav = _parse_nav(paths)
    store_cached(target, lambda tmp: tmp.write_bytes(pickle.dumps(nav, protocol=pickle.HIGHEST_PROTOCOL)))
    return nav


def _rename(notes: tuple[str, ...], old: tuple[str, ...], new: tuple[str, ...]) -> tuple[str, ...]:
    """Notes of a cached parse, naming the files of this call (the same content may have other names)."""
    out = []
    for note in notes:
        hits = [i for i, o in enumerate(old) if note.startswith(o + ":")]
        i = max(hits, key=lambda k: len(old[k]), default=None)
        out.append(note if i is None else new[i] + note[len(old[i]):])
    return tuple(dict.fromkeys(out))


def _parse_nav(paths: list[Path]) -> Navigation:
    import pandas as pd  # only when parsing: pandas costs ~0.4 s of start-up

    kep_frames, glo_frames, iono, notes = [], [], {}, []
    for path in paths:
        try:
            datasets, skipped = _read(path)
        except RinexError as err:       # a met, obs or SBAS file among several (a glob over a station's folder)
            if len(paths) == 1 or not err.reason.startswith((NOT_NAVIGATION, NO_SUPPORTED)):
                raise
            notes.append(f"{path}: {err.reason}: {LEFT_OUT}")
            continue
        notes += skipped
        raw = pd.concat([_flat(ds) for ds in datasets], ignore_index=True)
        kep, kep_notes = _plausible(_kepler_frame(raw), KEPLER_LIMITS)
        glo, glo_notes = _plausible(_glonass_frame(raw), GLONASS_LIMITS)
        impossible = kep_notes + glo_notes
        if kep.empty and glo.empty:
            if len(paths) > 1 and not impossible:   # no record of a system lfgnss reads (SBAS, IRNSS): of no use
                notes.append(f"{path}: {NO_SUPPORTED}: {LEFT_OUT}")
                continue
            first = f": every record impossible, e.g. {impossible[0]}" if impossible else ""
            raise RinexError(path, f"{NO_SUPPORTED}{first}")
        notes += [f"{path}: {note}" for note in impossible]
        kep_frames.append(kep)
        glo_frames.append(glo)
        for key, name in (("GPS", "ionospheric_corr_GPS"), ("BDS", "ionospheric_corr_BDS")):
            coef = np.asarray(datasets[0].attrs.get(name, []), dtype=float).ravel()
            if key not in iono and coef.size == 8 and np.all(np.isfinite(coef)) and np.any(coef != 0):
                iono[key] = coef    # all zero: a writer's placeholder, which would hide another file's values
    if not kep_frames:
        if any(f": {NO_SUPPORTED}" in n for n in notes if n.endswith(LEFT_OUT)):    # an SBAS file among them
            raise RinexError(paths[0], f"{NO_SUPPORTED} in any of the {len(paths)} files given")
        raise RinexError(paths[0], f"{NOT_NAVIGATION}, nor is any other of the {len(paths)} files given")
    kepler = _kepler_records(pd.concat(kep_frames, ignore_index=True))
    glonass = _glonass_records(pd.concat(glo_frames, ignore_index=True))
    return Navigation(kepler=kepler, glonass=glonass, iono=iono, sources=tuple(str(p) for p in paths),
                      warnings=tuple(dict.fromkeys(notes)))


#: Bounds of a broadcast value any GNSS satellite can have, (column, low, high, what): a record outside them is
#: damaged (a flipped exponent, a wrong field), and one such satellite would wreck every epoch's coarse fix.
#: sqrt(A) 4000-7500 m^0.5 spans 16 000-56 000 km (MEO to GEO; Galileo's eccentric E14/E18 included, e 0.16);
#: clock offsets: GPS/BeiDou fields reach 1 ms, Galileo's 62 ms, GLONASS tau_n 2 ms.
KEPLER_LIMITS = (("sqrt_a_sqrt_m", 4000.0, 7500.0, "sqrt(A) [m^0.5]"), ("e", 0.0, 0.5, "eccentricity"),
                 ("af0_s", -0.1, 0.1, "clock offset af0 [s]"))
GLONASS_LIMITS = (("radius_m", 2.0e7, 3.5e7, "orbit radius [m]"), ("speed_m_s", 0.0, 1.0e4, "speed [m/s]"),
                  ("tau_n_s", -0.01, 0.01, "clock offset tau_n [s]"),
                  # the ICD's field reaches 1.4e-5 m/s^2 (15 x 2^-30 km/s^2); a 3.05 status line read as an orbit
                  # line gives the URAI there (15 km/s^2 for an unknown accuracy)
                  ("acc_m_s2", 0.0, 1.0e-4, "luni-solar acceleration [m/s^2]"))


#: QZSS health bits that concern L1 C/A users: RTKLIB masks the lowest (L6/LEX) bit (``svh &= 0xFE``, satexclude).
QZSS_HEALTH_MASK = 0xFE


def effective_health(system: np.ndarray, health: np.ndarray) -> np.ndarray:
    """The health words that exclude a satellite from L1 single-frequency use: QZSS's without its L6 bit."""
    health = np.asarray(health).astype(int)
    return np.where(np.asarray(system) == "J", health & QZSS_HEALTH_MASK, health)


def _plausible(df: pd.DataFrame, limits: tuple) -> tuple[pd.DataFrame, list[str]]:
    """The records of ``df`` whose values are within ``limits`` (or that are flagged unhealthy, so never used),
    and one note per satellite with records skipped (without the file name)."""
    if df.empty:
        return df, []
    values = {"radius_m": lambda: np.linalg.norm(df[["x", "y", "z"]].to_numpy(float), axis=1),
              "speed_m_s": lambda: np.linalg.norm(df[["vx", "vy", "vz"]].to_numpy(float), axis=1),
              "acc_m_s2": lambda: np.linalg.norm(df[["ax", "ay", "az"]].to_numpy(float), axis=1)}
    bad = np.zeros(len(df), bool)
    system = df["system"].to_numpy() if "system" in df else np.full(len(df), "R")
    unhealthy = effective_health(system, df["health"].to_numpy()) != 0   # unusable anyway: kept, its flag in force
    why = np.full(len(df), "", dtype=object)
    for column, low, high, what in limits:
        v = values[column]() if column in values else df[column].to_numpy(float)
        out = ~bad & ~unhealthy & ~((v >= low) & (v <= high))
        why[out] = [f"{what} {x:.6g} outside [{low:g}, {high:g}]" for x in v[out]]
        bad |= out
    sv = df["sv"].to_numpy()
    notes = []
    for name in dict.fromkeys(sv[bad]):
        rows = np.flatnonzero(bad & (sv == name))
        notes.append(f"{len(rows)} {name} record(s) skipped as impossible, first: {why[rows[0]]}")
    return df[~bad], notes


# --------------------------------------------------------------------------------------------------
def _read(path: Path) -> tuple[list, list[str]]:
    """georinex.load on a cleaned copy of the file; every failure becomes a one-line RinexError.

    Returns one xarray Dataset per chunk of records (see :func:`_clean_layers`) and the notes on
    what was skipped.
    """
    import georinex
    from georinex.rio import opener

    if not path.is_file():
        raise RinexError(path, "a folder, not a navigation file" if path.is_dir() else "file not found")
    if path.stat().st_size == 0:
        raise RinexError(path, "empty file")
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise RinexError(path, f"cannot read file ({exc.strerror or exc})") from None
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if raw[:3] == b"BZh" or raw[:2] == b"PK":
                with opener(path) as f:   # georinex's reader for bzip2 and zip
                    text = f.read()
                notes: list[str] = []
            else:
                # plain, gzip (also cut short), .Z, Hatanaka; one character per byte, so a non-ASCII
                # byte stays where it was instead of shifting the fixed-width fields after it
                text, notes = _decode(raw, path)
            layers, skipped = _clean_layers(text, path)
            datasets = [georinex.load(io.StringIO(layer)) for layer in layers]
    except RinexError:
        raise
    except Exception as exc:  # georinex raises ValueError, KeyError, IndexError, OSError, ...
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise RinexError(path, f"not a readable RINEX navigation file ({reason})") from exc
    for ds in datasets:
        if ds is None or not hasattr(ds, "attrs") or not hasattr(ds, "data_vars"):
            raise RinexError(path, "not a readable RINEX navigation file")
        if ds.attrs.get("rinextype") != "nav":
            raise RinexError(path, f"not a RINEX navigation file (type {ds.attrs.get('rinextype')!r})")
    return datasets, notes + skipped


_RECORD_START = {2: re.compile(r"^[ 0-9][0-9] [ 0-9][0-9] [ 0-9][0-9] [ 0-9][0-9] "),
                 3: re.compile(r"^[GRECJSI][ 0-9][0-9] [0-9]{4} ")}
_FIELD_W = 19
_LOWER_D = re.compile(r"(?<=\d)d(?=[+-]?\d)")
_ZERO_FIELD = " 0.000000000000E+00"
# a value as georinex reads it (float() after D -> E), without nan/inf, underscores or inner blanks
_NUMBER = re.compile(r" *[+-]?(\d+\.?\d*|\.\d+)([EeD][+-]?\d+)? *")
_COMPLETE_NUMBER = re.compile(r" *[+-]?(\d+\.?\d*|\.\d+)[EeD][+-]?\d\d+ *")
#: Lines per record: RINEX 3 by the record's system letter, RINEX 2 by the file type of the header.
_RECORD_LINES = {3: {"G": 8, "E": 8, "J": 8, "C": 8, "I": 8, "R": 4, "S": 4}, 2: {"N": 8, "E": 8, "G": 4}}
#: RINEX 3.05 added a fourth BROADCAST ORBIT line to GLONASS records (status flags, L1/L2 group delay
#: difference, URAI, health flags): 5 lines from version 3.05 on. lfgnss uses none of its values; the line is
#: checked like the others, then dropped before georinex (1.16 reads 4 lines) sees the record. A 3.05 file whose
#: GLONASS records all keep the 4-line layout is read in that layout.
_GLONASS_LINES_V305 = 5


def _epoch_ok(line: str, version: int) -> bool:
    """Whether the satellite number and epoch of a record's first line are valid (georinex skips others)."""
    try:
        if version == 3:
            prn = int(line[1:3])
            dt.datetime(int(line[4:8]), int(line[9:11]), int(line[12:14]), int(line[15:17]), int(line[18:20]),
                        int(line[21:23]))
        else:
            prn = int(line[:2])
            year, second = int(line[3:5]), float(line[17:22])
            dt.datetime(year + (1900 if year >= 80 else 2000), int(line[6:8]), int(line[9:11]), int(line[12:14]),
                        int(line[15:17]), int(second))
            if not 0.0 <= second < 60.0:
                return False
    except ValueError:
        return False
    return prn > 0


def _record_problem(rec: list[str], version: int, n_lines: int, slots: list[tuple[int, int]],
                    cut: bool) -> tuple[int, str] | None:
    """(index of the damaged line, reason) for a record (lines padded to 80 columns) that cannot be read, or None.

    ``cut``: the file ends inside this record's last line (no newline at its end), so its last value may be cut.
    """
    if len(rec) != n_lines:
        what = "cut short" if len(rec) < n_lines else "too long (damaged, or merged with the next record)"
        return 0, f"record {what}: {len(rec)} lines instead of {n_lines}"
    epoch = rec[0][:slots[0][1]]
    if "\ufffd" in epoch:
        return 0, "non-ASCII bytes in the epoch line"
    if not _epoch_ok(rec[0], version):
        return 0, f"unreadable satellite number or epoch {epoch.strip()!r}"
    for j, c in slots:
        value = rec[j][c:c + _FIELD_W]
        if "\ufffd" in value:
            return j, f"non-ASCII bytes in value {value.strip().replace(chr(0xfffd), '?')!r}"
        if value.strip() and (not _NUMBER.fullmatch(value) or not np.isfinite(float(value.replace("D", "E")))):
            return j, f"unreadable value {value.strip()!r}"
    filled = [(j, c) for j, c in slots if rec[j][c:c + _FIELD_W].strip()]
    if cut and filled:
        j, c = filled[-1]
        if not _COMPLETE_NUMBER.fullmatch(rec[j][c:c + _FIELD_W]):
            return j, f"file ends inside value {rec[j][c:c + _FIELD_W].strip()!r}"
    return None


def _clean_layers(text: str, path: Path) -> tuple[list[str], list[str]]:
    """Skip damaged records and work around three georinex 1.16 defects without reading any value ourselves.

    0. A record with an unreadable value (text, non-ASCII bytes, nan/inf), an impossible epoch or a
       wrong number of lines makes georinex fail on the whole file (RINEX 2), silently drop it
       (RINEX 3) or read the next record's lines into it: such a record is skipped with a note
       ``PATH:LINE: reason``; all records damaged is an error.
    1. A blank field inside a record (BeiDou/Galileo "spare" fields) makes ``float('   ')`` fail and
       georinex silently turns the whole record into NaN (nav3) or crashes (nav2): interior blank
       fields are written as zeros, as RTKLIB reads them.
    2. Lines shorter than 80 columns shift every later field of the record: lines are padded.
    3. RINEX 2: two records of one satellite with the same epoch make georinex drop the satellite
       ("duplicate times detected, skipping SV"): exact duplicates are removed, and records that
       still share (sv, epoch) go to separate layers, each loaded on its own.

    Also, georinex's RINEX 3 reader merges satellites one by one into a growing xarray Dataset
    (seconds for a daily mixed file): there each satellite of each layer becomes its own small text.
    Returns the file as one or more RINEX texts (header + records), and the notes.
    """
    lines = text.replace("\r\n", "\n").replace("\r", "\n").split("\n")  # not splitlines: \f, \x1c... are no line ends
    end = next((i for i, ln in enumerate(lines) if "END OF HEADER" in ln), None)
    if end is None:
        raise RinexError(path, "no END OF HEADER line: not a RINEX file")
    try:
        full_version = float(lines[0][:9])
        version = int(full_version)
    except ValueError:
        raise RinexError(path, "first line has no RINEX version", line=1) from None
    record_lines = dict(_RECORD_LINES.get(version, {}))
    if version == 3 and full_version >= 3.05 - 1e-6:
        record_lines["R"] = _GLONASS_LINES_V305
    if version == 2 and lines[0][20:21] == "H":
        raise RinexError(path, f"{NO_SUPPORTED} (a RINEX 2 SBAS navigation file)", line=1)
    if version not in (2, 3) or not (lines[0][20:21] in ("N", "G", "E") or "NAV" in lines[0][20:40]):
        raise RinexError(path, f"{NOT_NAVIGATION} ({lines[0][:60].strip()!r})", line=1)
    start = _RECORD_START[version]
    first_col = 23 if version == 3 else 22
    cont_col = 4 if version == 3 else 3
    records: list[tuple[list[int], list[str]]] = []   # (line numbers, lines)
    orphans: list[int] = []
    for i, ln in enumerate(lines[end + 1:], start=end + 2):
        if start.match(ln) or version == 3 and _RECORD_START[2].match(ln):   # a RINEX 2 epoch line in a 3.0x
            records.append(([i], [ln]))         # file is a (damaged) record of its own, not part of the one before
        elif records and ln.strip():
            records[-1][0].append(i)
            records[-1][1].append(ln)
        elif ln.strip():
            orphans.append(i)
    notes = [f"{path}:{orphans[0]}: {len(orphans)} line(s) before the first ephemeris record skipped"] if orphans else []
    cut_line = len(lines) if lines[-1].strip() else None   # the file ends without a newline
    if record_lines.get("R") == _GLONASS_LINES_V305:
        # A writer that labels its files 3.05 but keeps the 4-line layout (no status line, which lfgnss drops anyway):
        # two or more whole GLONASS records of 4 lines and none of 5 make that the file's layout. A record cut by
        # the file's end is not counted; one short record among 5-line ones, or a lone one, stays damaged.
        sizes = [len(rec) for numbers, rec in records if rec[0][:1] == "R" and numbers[-1] != cut_line]
        if sizes.count(_GLONASS_LINES_V305 - 1) >= 2 and _GLONASS_LINES_V305 not in sizes:
            record_lines["R"] = _GLONASS_LINES_V305 - 1
    seen: set[tuple[str, ...]] = set()
    count: dict[str, int] = {}
    chunks: dict[tuple[int, str], list[str]] = {}
    damaged: list[tuple[int, str]] = []   # (line, reason) of each skipped record
    for numbers, rec in records:
        rec = [_LOWER_D.sub("D", ln).ljust(80)[:80] for ln in rec]   # 1.5d-04: Fortran's other exponent letter
        n_lines = record_lines.get(rec[0][0] if version == 3 else lines[0][20], 8)
        if numbers[-1] == cut_line and len(rec) == n_lines + 1:   # a file cut inside the next epoch line
            notes.append(f"{path}:{cut_line}: file ends inside this line; skipped")
            numbers, rec = numbers[:-1], rec[:-1]
        slots = [(0, first_col + k * _FIELD_W) for k in range(3)]
        slots += [(j, cont_col + k * _FIELD_W) for j in range(1, len(rec)) for k in range(4)]
        problem = _record_problem(rec, version, n_lines, slots, numbers[-1] == cut_line)
        if problem is not None:
            sv = rec[0][:3] if version == 3 else {"N": "G", "G": "R", "E": "E"}.get(lines[0][20], "?") + rec[0][:2]
            sv = sv.replace(" ", "0")
            damaged.append((numbers[problem[0]], f"{problem[1]}; {sv} record of line {numbers[0]} skipped"))
            continue
        for j, c in slots:        # every blank field, trailing ones too (a fit interval, BeiDou's AODC left out)
            if not rec[j][c:c + _FIELD_W].strip():
                rec[j] = rec[j][:c] + _ZERO_FIELD + rec[j][c + _FIELD_W:]
        if version == 3 and rec[0][0] == "R" and n_lines == _GLONASS_LINES_V305:
            rec = rec[:4]   # the RINEX 3.05 status line: georinex would read it as the start of a record
        key = tuple(rec)
        if key in seen:
            continue
        seen.add(key)
        ident = rec[0][:first_col]
        n = count.get(ident, 0)
        count[ident] = n + 1
        chunks.setdefault((n, rec[0][:3] if version == 3 else ""), []).extend(rec)
    if not chunks and damaged:
        raise RinexError(path, f"not a readable RINEX navigation file: all {len(damaged)} ephemeris record(s) "
                               f"damaged; first: {damaged[0][1]}", line=damaged[0][0])
    if not chunks:
        raise RinexError(path, "no ephemeris records")
    head = [_header_line(ln) for ln in lines[: end + 1] if not ln[60:].startswith(_UNUSED_HEADER_LABELS)]
    notes += [f"{path}:{line}: {reason}" for line, reason in damaged]
    return ["\n".join(head + chunk) + "\n" for chunk in chunks.values()], notes


#: Header lines lfgnss does not use, left out before georinex sees them: one blank number in them made it refuse the
#: whole file (RTKLIB reads blanks as 0).
_UNUSED_HEADER_LABELS = ("TIME SYSTEM CORR", "DELTA-UTC", "CORR TO SYSTEM TIME", "D-UTC A0,A1,T,W,S,U")
#: Ionosphere header lines and where their 4 numbers (12 columns each) start, RINEX 3 and 2.
_IONO_FIELDS = {"IONOSPHERIC CORR": 5, "ION ALPHA": 2, "ION BETA": 2}


def _header_line(line: str) -> str:
    """A header line as georinex reads it: ``d`` exponents as ``D`` (ION ALPHA 1.2d-08); a blank number of an
    ionosphere line as 0, as RTKLIB reads it (georinex refused the file)."""
    if "COMMENT" in line[60:]:
        return line
    line = _LOWER_D.sub("D", line)
    start = next((c for label, c in _IONO_FIELDS.items() if line[60:].startswith(label)), None)
    if start is not None:
        line = line.ljust(80)
        for k in range(4):
            c = start + 12 * k
            if not line[c:c + 12].strip():
                line = line[:c] + "  0.0000D+00" + line[c + 12:]
    return line


def _adjweek(sow_s: np.ndarray, ref_s: np.ndarray) -> np.ndarray:
    """Seconds of week -> seconds since 1980-01-06 in the week nearest ``ref_s`` (RTKLIB ``adjweek``)."""
    t = np.floor(ref_s / SECONDS_PER_WEEK) * SECONDS_PER_WEEK + sow_s
    t = np.where(t - ref_s < -SECONDS_PER_WEEK / 2, t + SECONDS_PER_WEEK, t)
    return np.where(t - ref_s > SECONDS_PER_WEEK / 2, t - SECONDS_PER_WEEK, t)


def _flat(ds) -> pd.DataFrame:
    """One row per (time, sv) cell of a georinex Dataset that holds a record (cheaper than to_dataframe)."""
    import pandas as pd

    if "sv" not in ds.dims or "time" not in ds.dims or ds.sizes["time"] == 0 or ds.sizes["sv"] == 0:
        return pd.DataFrame()
    names = [n for n in ds.data_vars if ds[n].dims == ("time", "sv")]
    nt, ns = ds.sizes["time"], ds.sizes["sv"]
    cols = {n: ds[n].values.reshape(-1) for n in names}
    has = np.zeros(nt * ns, bool)
    for key in ("sqrtA", "X"):
        if key in cols:
            has |= np.isfinite(cols[key])
    out = {"time": np.repeat(ds["time"].values, ns)[has],
           # georinex renames duplicate records of one satellite 'G05_1'; the suffix carries no information
           "sv": np.tile(np.asarray(ds["sv"].values).astype("<U3"), nt)[has]}
    out.update({n: v[has] for n, v in cols.items()})
    return pd.DataFrame(out)


def _frame(raw: pd.DataFrame, prefixes: tuple[str, ...], required: str) -> pd.DataFrame:
    """Rows of the satellites whose id starts with one of ``prefixes`` and have ``required``."""
    import pandas as pd

    if raw.empty or required not in raw:
        return pd.DataFrame()
    keep = raw["sv"].str[0].isin(prefixes).to_numpy() & np.isfinite(raw[required].to_numpy(dtype=float))
    return raw[keep].reset_index(drop=True)


def _col(df: pd.DataFrame, name: str) -> np.ndarray:
    return df[name].to_numpy(dtype=float) if name in df else np.full(len(df), np.nan)


def _kepler_frame(raw: pd.DataFrame) -> pd.DataFrame:
    import pandas as pd

    df = _frame(raw, KEPLER_SYSTEMS, "sqrtA")
    if df.empty:
        return df
    system = df["sv"].str[0].to_numpy()
    is_c = system == "C"
    toc_sys = datetime64_to_gps_s(df["time"].to_numpy())       # stamp in the system's own scale
    toe_sys = _adjweek(_col(df, "Toe"), toc_sys)
    ttr_sys = _adjweek(_col(df, "TransTime"), toc_sys)
    shift = np.where(is_c, -BDT_MINUS_GPST_S, 0.0)              # BDT -> GPST: +14 s
    tgd = _col(df, "TGD")
    tgd = np.where(is_c, _col(df, "TGD1"), tgd)
    src = np.nan_to_num(_col(df, "DataSrc")).astype(np.int64)
    is_e = system == "E"
    fnav_only = is_e & ((src & _GAL_INAV_BITS) == 0) & ((src & _GAL_FNAV_BIT) != 0)
    tgd = np.where(is_e, np.where(fnav_only, _col(df, "BGDe5a"), _col(df, "BGDe5b")), tgd)
    iode = np.full(len(df), np.nan)
    health = np.full(len(df), np.nan)
    for s in KEPLER_SYSTEMS:
        m = system == s
        iode[m] = _col(df, _IODE_NAME[s])[m]
        health[m] = _col(df, _HEALTH_NAME[s])[m]
    accuracy = np.where(is_e, _col(df, "SISA"), _col(df, "SVacc"))
    out = pd.DataFrame({
        "sv": df["sv"].to_numpy(), "system": system,
        "toe_gps_s": toe_sys + shift, "toc_gps_s": toc_sys + shift, "ttr_gps_s": ttr_sys + shift,
        "sqrt_a_sqrt_m": _col(df, "sqrtA"), "e": _col(df, "Eccentricity"), "i0_rad": _col(df, "Io"),
        "omega0_rad": _col(df, "Omega0"), "omega_rad": _col(df, "omega"), "m0_rad": _col(df, "M0"),
        "delta_n_rad_s": _col(df, "DeltaN"), "omega_dot_rad_s": _col(df, "OmegaDot"),
        "idot_rad_s": _col(df, "IDOT"), "cuc_rad": _col(df, "Cuc"), "cus_rad": _col(df, "Cus"),
        "crc_m": _col(df, "Crc"), "crs_m": _col(df, "Crs"), "cic_rad": _col(df, "Cic"),
        "cis_rad": _col(df, "Cis"), "af0_s": _col(df, "SVclockBias"), "af1_s_s": _col(df, "SVclockDrift"),
        "af2_s_s2": _col(df, "SVclockDriftRate"), "tgd_s": np.nan_to_num(tgd),
        "health": np.nan_to_num(health), "iode": np.nan_to_num(iode), "accuracy_m": np.nan_to_num(accuracy),
        "_fnav_only": fnav_only,
    })
    core = ["toe_gps_s", "toc_gps_s", "sqrt_a_sqrt_m", "e", "m0_rad", "af0_s"]
    bad = ~np.isfinite(out[core].to_numpy(dtype=float)).all(axis=1)
    return out[~bad].fillna({c: 0.0 for c in out.columns if c not in ("sv", "system", "ttr_gps_s")})


def _glonass_channel(freq_num: np.ndarray) -> np.ndarray:
    """Frequency channel numbers k of GLONASS records: a blank one is 0 (as RTKLIB reads blanks), one written as an
    unsigned byte (249 for -7) is brought back to -7..13 as RTKLIB's ``decode_geph`` does (``frq -= 256``)."""
    k = np.nan_to_num(freq_num)
    return np.where(k > 128, k - 256, k)


def _glonass_frame(raw: pd.DataFrame) -> pd.DataFrame:
    import pandas as pd

    df = _frame(raw, ("R",), "X")
    if df.empty:
        return df
    # GLONASS epochs are UTC, on a 15 min grid: RTKLIB's decode_geph rounds them to it (copies of a record stamped
    # 17 s late, as brdc1580.16g has at 12:15, would else put their satellites 60 km off for 15 minutes)
    utc_s = datetime64_to_gps_s(df["time"].to_numpy())      # UTC seconds since 1980-01-06
    toe = utc_to_gps_s(np.floor((utc_s + 450.0) / 900.0) * 900.0)
    pos = np.column_stack([_col(df, c) for c in ("X", "Y", "Z")])
    vel = np.column_stack([_col(df, c) for c in ("dX", "dY", "dZ")])
    acc = np.column_stack([_col(df, c) for c in ("dX2", "dY2", "dZ2")])
    radius = np.linalg.norm(pos, axis=1)
    if np.nanmedian(radius) < 1e5:  # georinex 1.16 converts km to m; guard against a version that doesn't
        pos, vel, acc = pos * 1e3, vel * 1e3, acc * 1e3
    tof = _col(df, "MessageFrameTime")
    out = pd.DataFrame({
        "sv": df["sv"].to_numpy(), "toe_gps_s": toe, "tof_s": tof,
        "x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2], "vx": vel[:, 0], "vy": vel[:, 1], "vz": vel[:, 2],
        "ax": np.nan_to_num(acc[:, 0]), "ay": np.nan_to_num(acc[:, 1]), "az": np.nan_to_num(acc[:, 2]),
        "tau_n_s": -_col(df, "SVclockBias"), "gamma_n": np.nan_to_num(_col(df, "SVrelFreqBias")),
        "k": _glonass_channel(_col(df, "FreqNum")), "health": np.nan_to_num(_col(df, "health")),
    })
    core = ["toe_gps_s", "x", "y", "z", "vx", "vy", "vz", "tau_n_s"]
    return out[np.isfinite(out[core].to_numpy(dtype=float)).all(axis=1)]


def _kepler_records(df: pd.DataFrame) -> KeplerEphemerides:
    names = [f.name for f in fields(KeplerEphemerides)]
    if df.empty:
        return KeplerEphemerides(**{n: np.zeros(0, dtype="<U3" if n == "sv" else "<U1" if n == "system"
                                                 else int if n in ("health", "iode") else float)
                                    for n in names})
    df = df.drop_duplicates(subset=[c for c in df.columns if c != "ttr_gps_s"])
    # Galileo: drop F/NAV records of satellites that also have I/NAV (E1 users want E1/E5b clocks)
    has_inav = set(df.loc[(df["system"] == "E") & ~df["_fnav_only"], "sv"])
    df = df[~(df["_fnav_only"] & df["sv"].isin(has_inav))]
    df = df.sort_values(["sv", "toe_gps_s", "ttr_gps_s"], kind="stable", na_position="first")
    cols = {n: df[n].to_numpy() for n in names}
    cols["sv"] = cols["sv"].astype("<U3")
    cols["system"] = cols["system"].astype("<U1")
    cols["health"] = cols["health"].astype(int)
    cols["iode"] = cols["iode"].astype(int)
    for n in names:
        if n not in ("sv", "system", "health", "iode"):
            cols[n] = cols[n].astype(float)
    return KeplerEphemerides(**cols)


def _glonass_records(df: pd.DataFrame) -> GlonassEphemerides:
    if df.empty:
        z = np.zeros(0)
        return GlonassEphemerides(sv=np.zeros(0, "<U3"), toe_gps_s=z, tof_s=z, pos_ecef_m=np.zeros((0, 3)),
                                  vel_ecef_m_s=np.zeros((0, 3)), acc_ecef_m_s2=np.zeros((0, 3)), tau_n_s=z,
                                  gamma_n=z, k=np.zeros(0, int), health=np.zeros(0, int))
    df = df.drop_duplicates(subset=[c for c in df.columns if c != "tof_s"])
    df = df.sort_values(["sv", "toe_gps_s", "tof_s"], kind="stable", na_position="first")
    return GlonassEphemerides(
        sv=df["sv"].to_numpy().astype("<U3"), toe_gps_s=df["toe_gps_s"].to_numpy(float),
        tof_s=df["tof_s"].to_numpy(float),
        pos_ecef_m=df[["x", "y", "z"]].to_numpy(float), vel_ecef_m_s=df[["vx", "vy", "vz"]].to_numpy(float),
        acc_ecef_m_s2=df[["ax", "ay", "az"]].to_numpy(float), tau_n_s=df["tau_n_s"].to_numpy(float),
        gamma_n=df["gamma_n"].to_numpy(float), k=df["k"].to_numpy().astype(int),
        health=df["health"].to_numpy().astype(int),
    )
