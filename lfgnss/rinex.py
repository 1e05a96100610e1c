"""RINEX observation reading: one entry point, ``load_obs``, returning ``Observations``.

Headers are read with georinex (``rinexinfo``, ``obsheader2``/``obsheader3``). Records are cut
from their fixed-width columns with one vectorised pass over all lines: georinex's own record
readers build one xarray object per epoch (about 4 ms per epoch and constellation, 26 s for
``hk-tst-2019``), which is 100x slower; ``engine="georinex"`` keeps that path, and the tests check
that both give the same numbers on the shared data. A bad record is skipped with a warning naming
the file and line; a file that cannot be used at all raises :class:`RinexError`.
Parsed files are cached on disk keyed by their content (``lfgnss.paths.cache_dir()``).
"""
from __future__ import annotations

import datetime as dt
import hashlib
import io
import json
import re
import warnings
import zlib
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .constants import SYSTEMS
from .errors import RinexError
from .observations import Observations
from .paths import cache_file, load_cached, store_cached
from .time import datetime64_to_gps_s, utc_to_gps_s

if TYPE_CHECKING:
    import pandas as pd

_PARSER_VERSION = 10      # 10: types an event redefines; 9: repeated types go on, Doppler order; 8: 0.000 pseudoranges,
#                           events, code order
_GPS_EPOCH = dt.datetime(1980, 1, 6)
_SV_RE = re.compile(r"^[GRECJSI][ 0-9][0-9]$")
_V2_RECORD_LIKE = re.compile(r"^[ 0-9.\-]*[0-9][ 0-9.\-]*$")  # digits, blanks, points, signs only
_V2_EPOCH_RE = re.compile(r"^ [ \d]\d [ \d]\d [ \d]\d [ \d]\d [ \d]\d [ \d]\d\.\d+ +[0-6][ \d]{3}")
#: An event line whose time is left blank, as RINEX 2.11 allows for flags 2-5: 28 blanks, the flag, the count of
#: special records (a record line never has column 27, the point of its second value, blank with a digit after it).
_V2_EVENT_RE = re.compile(r"^ {28}([2-5])([ \d]{2}\d)")
#: The same in RINEX 3: ">", blanks for the time, the flag and the count.
_V3_EVENT_RE = re.compile(r"^>\s+([2-5])\s+(\d{1,3})\s*$")
#: Header labels that redefine the observation types, found in an event's special records (flags 3 and 4).
_TYPES_LABELS = ("# / TYPES OF OBSERV", "SYS / # / OBS TYPES")
#: Character classes of an epoch line's first 19 characters, " yy mm dd hh mm ss.": a line that starts like
#: them is a damaged epoch line, never a record line (whose first field is a right-aligned F14.3 or blank).
_V2_EPOCH_START = (" ", " 0123456789", "0123456789") * 6 + (".",)
#: Columns 27-35 of an epoch line: two blanks, the flag, the satellite count and a first satellite id; in a
#: record line, column 27 is the decimal point of the second field or, that field blank, column 29 is blank.
_V2_EPOCH_TAIL = re.compile(r"^.{26}  [0-6][ \d]{2}\d[GRECJSI ][ \d]\d")


def _v2_epoch_start(line: str) -> bool:
    """True if ``line`` (at least 3 characters) begins like a RINEX 2 epoch line, e.g. one cut short."""
    head = line.rstrip()[:len(_V2_EPOCH_START)]
    return len(head) >= 3 and all(c in allowed for c, allowed in zip(head, _V2_EPOCH_START))


def _v2_damaged_epoch(line: str) -> bool:
    """True if ``line`` looks like a RINEX 2 epoch line (damaged or not), never for a record line: it begins
    like one, or has an epoch line's flag, satellite count and first satellite id in place."""
    return _v2_epoch_start(line) or _V2_EPOCH_TAIL.match(line) is not None

#: Pseudorange code preference per constellation (single frequency, L1/E1/B1I/G1); the first one the header
#: lists is used for the whole file (docs/input_conventions.md). BeiDou: B1I only, whatever the
#: label: RINEX 3.01 and 3.03+ call it band 2 (C2I/C2Q/C2X), RINEX 3.02 band 1 (C1I/C1Q/C1X); in 3.03+
#: band 1 is B1C (C1D/C1P/C1X), another signal with other group delays, which is not supported.
CODES_V3 = {"G": ("C1C", "C1P", "C1W", "C1X"), "R": ("C1C", "C1P"), "E": ("C1C", "C1B", "C1X"),
            "J": ("C1C", "C1L", "C1S", "C1X"), "C": ("C2I", "C2Q", "C2X", "C1I", "C1Q")}
# (in RTKLIB 2.4.3 b34's order, its codepris: GPS CPYWMNSL, GLONASS CPABX, Galileo CABXZ, QZSS CLSXZ, BeiDou
# IQXDPAN; GPS C1X, L1C, is lfgnss's own last resort, which RTKLIB refuses)
#: RINEX 3.00-3.02 BeiDou: 3.02 names B1I band 1; C2I/C2Q/C2X (the 3.01 and 3.03 labels, found in some
#: 3.02 files; RTKLIB 2.4.3 reads them as B1I) are B1I too. C1X is B1I only in a file without band-2 codes
#: (else it is 3.03's B1C, see ``_bds_codes``).
CODES_V302_BDS = ("C1I", "C1X", "C2I", "C2X", "C1Q", "C2Q")
#: BeiDou B1C codes of RINEX 3.03+ (not supported: B1C needs its own group delays, absent from D1/D2 nav).
BDS_B1C_CODES = ("C1D", "C1P", "C1X")
#: RINEX 2: the first code of each list is preferred; where it is blank for a satellite, the next one the
#: header lists is used for that record (C1 -> P1, as RTKLIB does for RINEX <= 2.11), with a note.
CODES_V2 = {"G": ("C1", "P1"), "R": ("C1", "P1"), "E": ("C1",), "J": ("C1",), "C": ("C2", "C1")}
#: Time system of the epochs when the header leaves it blank, by the file's satellite system (RINEX 2.11 and
#: 3.0x "TIME OF FIRST OBS": GPS for pure GPS files, GLO for pure GLONASS, BDT for pure BeiDou, ...).
_DEFAULT_TIME_SYSTEM = {"R": "GLO", "C": "BDT", "E": "GAL", "J": "QZS", "I": "IRN"}
#: Time systems an observation file's "TIME OF FIRST OBS" may name (RINEX 3.05 table A2); others are read as GPS.
_TIME_SYSTEMS = ("GPS", "GLO", "GAL", "QZS", "BDT", "IRN")


class RinexWarning(UserWarning):
    """Records, epochs or constellations of a RINEX file were skipped, or a pseudorange code substituted."""


def load_obs(path: str | Path, *, systems: tuple[str, ...] | None = None, cache: bool = True,
             engine: str = "lfgnss") -> Observations:
    """Read a RINEX 2.11/3.0x observation file (plain, gzip, .Z or Hatanaka) [m, dB-Hz, Hz].

    Parameters
    ----------
    path : observation file.
    systems : constellation letters to keep (default: every supported one present).
    cache : reuse/write the parsed result in the cache, keyed by file content.
    engine : ``"lfgnss"`` (vectorised records) or ``"georinex"`` (georinex records, slow).
    """
    path = Path(path)
    raw = _read_bytes(path)
    key = hashlib.sha256(raw).hexdigest()[:24] + f"-v{_PARSER_VERSION}-{engine}"
    cached = cache_file("obs", f"{key}.npz") if cache else None
    obs = load_cached(cached, lambda entry: _from_npz(entry, path))
    if obs is None:
        text, notes = _decode(raw, path)
        obs = _parse(text, path, engine, notes)
        store_cached(cached, lambda tmp: _to_npz(tmp, obs))
    if obs.warnings:  # also on a cache hit: the same file always gives the same warning
        warnings.warn(f"{path}: {len(obs.warnings)} problem(s) (damaged records or epochs skipped, constellations "
                      f"or codes not usable or substituted); first: {obs.warnings[0]}", RinexWarning, stacklevel=2)
    return obs.select_systems(systems) if systems else obs


def _read_bytes(path: Path) -> bytes:
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise RinexError(path, f"cannot read file ({err.strerror or err})") from None
    if not raw.strip():
        raise RinexError(path, "file is empty")
    return raw


def _decode(raw: bytes, path: Path) -> tuple[str, list[str]]:
    """Text of the file, decompressed (gzip, .Z, Hatanaka), CRLF normalised, non-ASCII bytes replaced.

    A gzip stream that ends early (interrupted download) keeps what could be decompressed, with a
    note; the epoch cut in the middle is then dropped like any truncated epoch.
    """
    notes: list[str] = []
    if raw[:2] == b"\x1f\x8b":
        raw = _gunzip(raw, path, notes)
    if raw[:2] == b"\x1f\x9d" or b"COMPACT RINEX" in raw[:200]:
        import hatanaka

        try:
            raw = hatanaka.decompress(raw)
        except Exception as err:  # hatanaka raises assorted errors for damaged archives
            raise RinexError(path, f"cannot decompress ({type(err).__name__}: {err})") from None
    text = raw.decode("ascii", errors="replace")
    return text.replace("\r\n", "\n").replace("\r", "\n"), notes


def _gunzip(raw: bytes, path: Path, notes: list[str]) -> bytes:
    """Decompress every gzip member. A stream that ends early keeps the data before the cut (deflate
    output is an exact prefix of the original), with a note; damaged data (a bad block or checksum)
    are an error, since the damage may lie anywhere before the point where zlib notices it.
    """
    out: list[bytes] = []
    rest = raw
    while rest:
        d = zlib.decompressobj(wbits=31)
        try:
            out.append(d.decompress(rest))
            out.append(d.flush())
        except zlib.error as err:
            raise RinexError(path, f"cannot decompress: damaged gzip data ({err})") from None
        if not d.eof:
            size = sum(map(len, out))
            if size == 0:
                raise RinexError(path, "cannot decompress: gzip data end before any content")
            notes.append(f"{path}: compressed data end early (gzip data truncated): {size} bytes recovered, "
                         f"the rest of the file is lost")
            break
        rest = d.unused_data.lstrip(b"\0")  # next member; trailing zero padding is allowed
        if rest and rest[:2] != b"\x1f\x8b":
            notes.append(f"{path}: {len(rest)} bytes after the end of the gzip data ignored")
            break
    return b"".join(out)


def _split_header(text: str, path: Path) -> tuple[str, list[str], int]:
    end = text.find("END OF HEADER")
    if end < 0:
        raise RinexError(path, "no 'END OF HEADER' line: not a RINEX file or a truncated header")
    nl = text.find("\n", end)
    header = text[: nl + 1 if nl >= 0 else len(text)]
    body = text[len(header):].split("\n")
    return header, body, header.count("\n")


def _header_info(header: str, path: Path) -> dict:
    import georinex

    first = header.split("\n", 1)[0]
    if "RINEX VERSION" not in first:
        raise RinexError(path, "first line is not a 'RINEX VERSION / TYPE' header line", line=1)
    try:
        info = georinex.rinexinfo(io.StringIO(header))
    except Exception as err:
        raise RinexError(path, f"unreadable RINEX version line ({err})", line=1) from None
    version = float(info.get("version", 0.0))
    if info.get("rinextype") != "obs":
        raise RinexError(path, f"is a {info.get('rinextype', 'unknown')} file, not an observation file", line=1)
    if not (2.0 <= version < 5.0):
        raise RinexError(path, f"unsupported RINEX version {version} (supported: 2.x, 3.x, 4.x)", line=1)
    _check_type_counts(header, version, path)
    try:
        if version < 3:
            from georinex.obs2 import obsheader2

            hdr = obsheader2(io.StringIO(header))
        else:
            from georinex.obs3 import obsheader3

            hdr = obsheader3(io.StringIO(header))
    except Exception as err:
        label = "# / TYPES OF OBSERV" if version < 3 else "SYS / # / OBS TYPES"
        where = next((i + 1 for i, ln in enumerate(header.split("\n")) if label in ln), None)
        raise RinexError(path, f"unreadable '{label}' header ({type(err).__name__}: {err})", line=where) from None
    lines = header.split("\n")
    if not hdr.get("fields"):
        other = "SYS / # / OBS TYPES" if version < 3 else "# / TYPES OF OBSERV"
        where = next((i + 1 for i, ln in enumerate(lines) if other in ln[60:]), None)
        if where is not None:  # e.g. a RINEX 2 body under a 3.02 version line
            raise RinexError(path, f"observation types given as '{other}' (RINEX {3 if version < 3 else 2}), but "
                                   f"line 1 says RINEX {version}: version and header disagree", line=where)
        raise RinexError(path, "header lists no observation types")
    notes = []
    where = next((i + 1 for i, ln in enumerate(lines) if "TIME OF FIRST OBS" in ln[60:]), None)
    time_system = lines[where - 1][48:60].strip() if where else ""
    if not time_system:  # blank: the default of the file's satellite system (column 41 of the version line)
        time_system = _DEFAULT_TIME_SYSTEM.get(first[40:41], "GPS")
    elif time_system not in _TIME_SYSTEMS:
        notes.append(f"{path}:{where}: unknown time system {time_system!r} in 'TIME OF FIRST OBS' (expected "
                     f"{'/'.join(_TIME_SYSTEMS)}): epoch times read as GPS time")
        time_system = "GPS"
    try:
        approx = np.array([float(v) for v in hdr.get("position", [0.0, 0.0, 0.0])][:3])
    except (TypeError, ValueError):
        approx = np.zeros(3)
    if approx.size != 3 or not np.all(np.isfinite(approx)):
        approx = np.zeros(3)
    return {"version": version, "fields": hdr["fields"], "time_system": time_system, "approx": approx, "notes": notes}


def _check_type_counts(header: str, version: float, path: Path) -> None:
    """Raise :class:`RinexError` where an observation-types header line declares another number of types than
    it (with its continuation lines) lists: records could not be cut into the right fields."""
    label = "# / TYPES OF OBSERV" if version < 3 else "SYS / # / OBS TYPES"
    groups: list[list] = []  # [line number, what, declared count text, listed types]
    for i, ln in enumerate(header.split("\n")):
        if label not in ln[60:]:
            continue
        if not groups or version >= 3 and ln[:1].strip():  # else a continuation line
            what = f" for {ln[0]}" if version >= 3 and ln[:1].strip() else ""
            groups.append([i + 1, what, (ln[:6] if version < 3 else ln[1:6]).strip(), []])
        groups[-1][3] += ln[6:60].split()
    for lineno, what, count, types in groups:
        if count.isdigit() and int(count) != len(types):
            raise RinexError(path, f"'{label}' header{what} declares {int(count)} observation types but lists "
                                   f"{len(types)} ({' '.join(types)})", line=lineno)


def _bds_codes(types: list[str], version: float) -> tuple[str, ...]:
    """BeiDou B1I pseudorange codes in order of preference for a RINEX 3 header listing ``types``."""
    if version >= 3.03:
        return CODES_V3["C"]
    if any(t in types for t in ("C2I", "C2Q", "C2X")):  # band 2 is B1I, so band-1 X would be 3.03's B1C
        return tuple(c for c in CODES_V302_BDS if c != "C1X")
    return CODES_V302_BDS


def _choose_codes(fields, version: float, path: Path, problems: list[str], required: bool = True
                  ) -> dict[str, tuple]:
    """Per constellation: column index of pseudorange, C/N0, Doppler (-1 if absent), the code, and the
    column and code of the RINEX 2 fallback pseudorange (-1 and "" if none). None at all: RinexError if
    ``required`` (a header), else {} (the constellations an event adds)."""
    chosen = {}
    for system in SYSTEMS:
        if version < 3:
            types = list(fields)
            prefs = CODES_V2[system]
        else:
            if system not in fields:
                continue
            types = list(fields[system])
            prefs = _bds_codes(types, version) if system == "C" else CODES_V3[system]
        code = next((c for c in prefs if c in types), None)
        if code is None:
            if version >= 3:
                why = ""
                b1c = [t for t in types if t in BDS_B1C_CODES] if system == "C" and version >= 3.03 else []
                if b1c:
                    why = (f"; {'/'.join(b1c)} {'is' if len(b1c) == 1 else 'are'} B1C, not supported "
                           f"(lfgnss uses B1I: C2I/C2X/C2Q)")
                problems.append(f"{path}: {system} has no supported pseudorange type (has {' '.join(types)}){why}; "
                                f"its satellites are skipped")
            continue
        cn0 = ("S" + code[1:]) if ("S" + code[1:]) in types else ("S1" if "S1" in types and version < 3 else None)
        # the code's own Doppler, else another of its band in the order of preference of the codes (a carrier's
        # Doppler does not depend on the code)
        band = sorted((t for t in types if t[:2] == "D" + code[1]),
                      key=lambda t: prefs.index("C" + t[1:]) if "C" + t[1:] in prefs else len(prefs))
        dop = ("D" + code[1:]) if ("D" + code[1:]) in types else (band[0] if band else None)
        fallback = next((c for c in prefs[prefs.index(code) + 1:] if c in types), None) if version < 3 else None
        chosen[system] = (types.index(code), types.index(cn0) if cn0 else -1, types.index(dop) if dop else -1, code,
                          types.index(fallback) if fallback else -1, fallback or "")
    if not chosen and required:
        raise RinexError(path, "no pseudorange observation type for any supported constellation "
                               "(need C1C/C1/C2I/...)")
    return chosen


def _to_gps_s(year: int, month: int, day: int, hour: int, minute: int, sec: float, time_system: str) -> float:
    t = (dt.datetime(year, month, day, hour, minute) - _GPS_EPOCH).total_seconds() + sec
    return float(_scale_to_gps_s(t, time_system))


def tags_to_gps_s(times: np.ndarray, time_system: str) -> np.ndarray:
    """GPS seconds since 1980-01-06 [s] from an observation file's datetime64 epoch tags on its ``time_system``
    (georinex's ``ds.time``; ``_scale_to_gps_s``)."""
    return _scale_to_gps_s(datetime64_to_gps_s(times), time_system)


def _scale_to_gps_s(t: np.ndarray | float, time_system: str) -> np.ndarray:
    """GPS seconds from epoch time tags counted since 1980-01-06 on the file's time scale [s].

    ``BDT``: + 14 s. ``GLO``: the tags are UTC(SU) (RINEX; not GLONASS system time, which is 3 h ahead),
    + leap seconds as RTKLIB does (``utc2gpst``). GPS, GAL, QZS and IRN are taken as GPS time.
    """
    if time_system == "BDT":
        return np.asarray(t, dtype=float) + 14.0
    if time_system == "GLO":
        return utc_to_gps_s(t)
    return np.asarray(t, dtype=float)


def _parse(text: str, path: Path, engine: str, notes: list[str] | None = None) -> Observations:
    header, body, n_header = _split_header(text, path)
    info = _header_info(header, path)
    problems: list[str] = list(notes or []) + info["notes"]
    codes = _choose_codes(info["fields"], info["version"], path, problems)
    if engine == "georinex":
        return _parse_georinex(text, path, info, codes, problems, _first_redefinition(body, n_header, info, path))
    cut = _cut_v2 if info["version"] < 3 else _cut_v3
    cuts: list[list] = [[] for _ in range(6)]   # epoch times and lines; records' epoch, id, text and line
    piece, start = info, 0
    pieces = []     # per redefinition: where its note goes in problems, its line, its types, its first record
    dropped: set[int] = set()
    while True:     # one piece of the file per set of observation types (an event may redefine them)
        *got, redefined = cut(body, n_header, path, piece, problems, start)
        got[2] = [e + len(cuts[0]) for e in got[2]]
        for whole, part in zip(cuts, got):
            whole += part
        if redefined is None:
            break
        at, start, fields = redefined
        if not fields:  # unreadable: the note is given
            break
        added = {} if info["version"] < 3 else {k: v for k, v in fields.items() if k not in info["fields"]}
        if added:       # a constellation the header lacks: its first types are its layout, as a header's would be
            info = dict(info, fields={**info["fields"], **added})
            codes = {**codes, **_choose_codes(added, info["version"], path, problems, required=False)}
            early = [k for k, sv in enumerate(cuts[3]) if sv[:1] in added]   # records before it had types
            if early:
                problems.append(f"{path}:{cuts[5][early[0]]}: {len(early)} record(s) of {''.join(sorted(added))} "
                                f"before the event on line {n_header + at + 1} gives their observation types (no "
                                f"header line for them): skipped")
                dropped.update(early)
        pieces.append((len(problems), n_header + at + 1, fields, len(cuts[3])))
        piece = dict(info, fields=fields)
    ends = [p[3] for p in pieces[1:]] + [len(cuts[3])]
    layouts: dict[str, list] = {}               # records of each set of types an event gave, read in one go
    for (where, lineno, fields, first), end in reversed(list(zip(pieces, ends))):
        rows = [k for k in range(first, end) if k not in dropped]   # not those of a constellation without types yet
        layouts.setdefault(repr(fields), [fields, []])[1].extend(rows)
        # only constellations with records in the piece: RINEX 2 types name none, and lfgnss's BeiDou ones (C2)
        # would be missed in a GPS and GLONASS file
        present = {(cuts[3][k][:1].strip() or "G") for k in rows}
        lacking = _lacking_types({k: v for k, v in codes.items() if k in present}, info["fields"], fields,
                                 info["version"])
        if lacking:
            problems.insert(where, f"{path}:{lineno}: the event here redefines the observation types without "
                                   f"{lacking}: read as missing from here on")
    for fields, rows in layouts.values():
        texts = _in_header_layout([cuts[3][k] for k in rows], [cuts[4][k] for k in rows], fields, info["fields"],
                                  info["version"])
        for k, text in zip(rows, texts):
            cuts[4][k] = text
    if dropped:
        for j in range(2, 6):
            cuts[j] = [v for k, v in enumerate(cuts[j]) if k not in dropped]
    return _assemble(path, info, codes, *cuts, problems)


def _epoch_fields(ln: str, v3: bool) -> tuple[int, int, int, int, int, float, int, int]:
    if v3:
        return (int(ln[2:6]), int(ln[7:9]), int(ln[10:12]), int(ln[13:15]), int(ln[16:18]), float(ln[18:29]),
                int(ln[31]), int(ln[32:35]))
    yy = int(ln[1:3])
    return (yy + (2000 if yy < 80 else 1900), int(ln[4:6]), int(ln[7:9]), int(ln[10:12]), int(ln[13:15]),
            float(ln[15:26]), int(ln[28]), int(ln[29:32]))


def _cut_v3(body, n_header, path, info, problems, start=0):
    """Epoch times and lines, and the raw record lines of every complete epoch (RINEX 3) from ``body[start]`` up to an
    event that redefines the observation types: then also (its index, the index after its special records, the new
    types)."""
    times, epoch_lines, rec_epoch, rec_sv, rec_text, rec_line = [], [], [], [], [], []
    i, n = start, len(body)
    while i < n:
        ln = body[i]
        lineno = n_header + i + 1
        if not ln.startswith(">"):
            if ln.strip():
                problems.append(f"{path}:{lineno}: line outside an epoch record, skipped")
            i += 1
            continue
        event = _V3_EVENT_RE.match(ln)
        if event:
            flag, nsat = int(event[1]), int(event[2])
            fields = _types_redefined(body[i + 1: i + 1 + nsat], info, path, lineno, problems)
            if fields is not None:
                return times, epoch_lines, rec_epoch, rec_sv, rec_text, rec_line, (i, i + 1 + nsat, fields)
            i += 1 + nsat
            continue
        try:
            y, mo, d, h, mi, s, flag, nsat = _epoch_fields(ln, True)
            if nsat < 0 or not 0 <= flag <= 6:  # a negative count would step backwards: endless loop
                raise ValueError
            t = _to_gps_s(y, mo, d, h, mi, s, info["time_system"])
        except (ValueError, IndexError):
            problems.append(f"{path}:{lineno}: unreadable epoch line, epoch skipped")
            i += 1
            while i < n and not body[i].startswith(">"):
                i += 1
            continue
        if flag > 1:  # event records: nsat special lines follow
            fields = _types_redefined(body[i + 1: i + 1 + nsat], info, path, lineno, problems) if flag <= 5 else None
            if fields is not None:
                return times, epoch_lines, rec_epoch, rec_sv, rec_text, rec_line, (i, i + 1 + nsat, fields)
            i += 1 + nsat
            continue
        recs = body[i + 1: i + 1 + nsat]
        stop = next((k for k, r in enumerate(recs) if r.startswith(">")), len(recs))
        if stop < nsat:
            problems.append(f"{path}:{lineno}: epoch truncated ({stop} of {nsat} satellite records), skipped")
            i += 1 + stop
            continue
        ep = len(times)
        times.append(t)
        epoch_lines.append(lineno)
        for k, r in enumerate(recs):
            rec_epoch.append(ep)
            rec_sv.append(r[:3])
            rec_text.append(r[3:])
            rec_line.append(lineno + 1 + k)
        i += 1 + nsat
    return times, epoch_lines, rec_epoch, rec_sv, rec_text, rec_line, None


def _cut_v2(body, n_header, path, info, problems, start=0):
    """Epoch times and lines, and per-satellite record strings of every complete epoch (RINEX 2), and where an
    event redefines the observation types, as ``_cut_v3``."""
    n_types = len(info["fields"])
    lines_per_sat = (n_types + 4) // 5
    times, epoch_lines, rec_epoch, rec_sv, rec_text, rec_line = [], [], [], [], [], []
    i, n = start, len(body)
    while i < n:
        ln = body[i]
        lineno = n_header + i + 1
        if not ln.strip():
            i += 1
            continue
        event = _V2_EVENT_RE.match(ln)
        try:
            if event:
                flag, nsat = int(event[1]), int(event[2])
            elif not _V2_EPOCH_RE.match(ln):
                raise ValueError
            else:
                y, mo, d, h, mi, s, flag, nsat = _epoch_fields(ln, False)
                t = _to_gps_s(y, mo, d, h, mi, s, info["time_system"])
        except (ValueError, IndexError):
            problems.append(f"{path}:{lineno}: unreadable epoch line, skipped up to the next epoch")
            i = _next_v2_epoch(body, i + 1)
            continue
        n_sv_lines = max(1, (nsat + 11) // 12)
        if flag == 6:   # cycle slips: satellite ids and records laid out as an epoch's, not used
            i += n_sv_lines + nsat * lines_per_sat
            continue
        if flag > 1:    # events: nsat special records
            fields = _types_redefined(body[i + 1: i + 1 + nsat], info, path, lineno, problems)
            if fields is not None:
                return times, epoch_lines, rec_epoch, rec_sv, rec_text, rec_line, (i, i + 1 + nsat, fields)
            i += 1 + nsat
            continue
        if any(i + k >= n or body[i + k][:32].strip() for k in range(1, n_sv_lines)):
            # a continuation line of satellite ids starts with 32 blanks; anything else means the epoch's
            # lines are shifted (a lost or repeated line) and its records would go to the wrong satellites
            problems.append(f"{path}:{lineno}: epoch line without its satellite-id continuation line, skipped "
                            f"up to the next epoch")
            i = _next_v2_epoch(body, i + 1)
            continue
        sv_text = "".join(body[i + k][32:68].ljust(36) for k in range(n_sv_lines) if i + k < n).ljust(3 * nsat)
        svs = [sv_text[3 * k: 3 * k + 3] for k in range(nsat)]
        svs = [("G" + s[1:]) if s[0] == " " and s[1:].strip() else s for s in svs]  # blank system letter: GPS
        first = i + n_sv_lines
        recs = body[first: first + nsat * lines_per_sat]
        bad = next((k for k, r in enumerate(recs) if _V2_EPOCH_RE.match(r) or _V2_EVENT_RE.match(r)
                    or _v2_damaged_epoch(r)), len(recs))
        if bad < nsat * lines_per_sat:
            problems.append(f"{path}:{lineno}: epoch truncated ({bad // lines_per_sat} of {nsat} satellite "
                            f"records), skipped")
            i = first + bad
            continue
        nxt = first + nsat * lines_per_sat
        while nxt < n and not body[nxt].strip():
            nxt += 1
        if (nxt < n and not _V2_EPOCH_RE.match(body[nxt]) and _V2_RECORD_LIKE.match(body[nxt])
                and not _V2_EVENT_RE.match(body[nxt]) and not _v2_damaged_epoch(body[nxt])):
            # one record line more than announced: a record was repeated or inserted, and since RINEX 2
            # records carry no satellite id, those after it would be matched to the wrong satellites
            problems.append(f"{path}:{lineno}: epoch followed by one record line more than its {nsat} "
                            f"satellites (line {n_header + nxt + 1}): records cannot be matched to satellites, "
                            f"skipped up to the next epoch")
            i = _next_v2_epoch(body, nxt + 1)
            continue
        ep = len(times)
        times.append(t)
        epoch_lines.append(lineno)
        for k, sv in enumerate(svs):
            chunk = recs[k * lines_per_sat:(k + 1) * lines_per_sat]
            rec_epoch.append(ep)
            rec_sv.append(sv)
            rec_text.append("".join(c[:80].ljust(80) for c in chunk))
            rec_line.append(first + 1 + n_header + k * lines_per_sat)
        i = first + nsat * lines_per_sat
    return times, epoch_lines, rec_epoch, rec_sv, rec_text, rec_line, None


def _next_v2_epoch(body: list[str], i: int) -> int:
    """Index of the first line from ``i`` on that is, or begins like, a RINEX 2 epoch line (``len(body)`` if
    none): a damaged epoch line is stopped at too, so that each one gets its own note (each costs an epoch)."""
    while i < len(body) and not (_V2_EPOCH_RE.match(body[i]) or _V2_EVENT_RE.match(body[i])
                                 or _v2_damaged_epoch(body[i])):
        i += 1
    return i


def _types_redefined(special: list[str], info: dict, path: Path, lineno: int, problems: list[str]
                     ) -> list[str] | dict[str, list[str]] | None:
    """The observation types an event's special records give where they differ from ``info``'s (RINEX 2: a list;
    3: a dict, the header's systems with theirs replaced), else None: the header's own types repeated (a spliced
    file) change nothing. Types it cannot read: a note, and an empty list or dict (the reading ends there)."""
    lines = [r for r in special if r[60:].strip().startswith(_TYPES_LABELS)]
    if not lines:
        return None
    label = next(lab for lab in _TYPES_LABELS if lines[0][60:].strip().startswith(lab))
    counts: list[list] = []     # [declared count, listed types] per system (RINEX 2: one)
    given: dict[str, list[str]] = {}
    for r in lines:
        system = "" if info["version"] < 3 else r[:1].strip()
        if not counts or system:    # else a continuation line
            counts.append([(r[:6] if info["version"] < 3 else r[3:6]).strip(), given.setdefault(system, [])])
        counts[-1][1] += r[6:60].split()
    if any(not c.isdigit() or int(c) != len(t) or not t for c, t in counts) or "" in given and info["version"] >= 3:
        problems.append(f"{path}:{lineno}: the event here redefines the observation types ({label.strip()}) in "
                        f"lines that cannot be read (a count that is not the number of types listed, none, or a "
                        f"continuation line first): the epochs from here on are left out")
        return [] if info["version"] < 3 else {}
    if info["version"] < 3:
        return None if given[""] == list(info["fields"]) else given[""]
    # a system lfgnss does not read (SBAS) shifts no column of the others: each record line names its system
    known = {s: t for s, t in given.items() if s in SYSTEMS}
    if all(list(info["fields"].get(s, [])) == t for s, t in known.items()):
        return None
    return {**info["fields"], **known}


def _in_header_layout(rec_sv: list[str], rec_text: list[str], fields, header_fields, version: float) -> list[str]:
    """Record texts laid out in ``fields`` (types an event gave), rearranged into the header's layout (16
    characters a value; a type the event dropped left blank), so one set of column indices reads every record."""
    import pandas as pd

    text = pd.Series(rec_text, dtype=object)
    system = pd.Series(rec_sv, dtype=object).str[:1].str.replace(" ", "G")
    out = text.copy()
    for letter in (["G"] if version < 3 else list(header_fields)):
        rows = np.ones(len(text), bool) if version < 3 else (system == letter).to_numpy()
        if not rows.any():
            continue
        new, old = list(fields if version < 3 else fields[letter]), list(header_fields if version < 3 else
                                                                         header_fields[letter])
        sub = text[rows].str.ljust(16 * len(new))
        blank = pd.Series(" " * 16, index=sub.index)
        out[rows] = sum((sub.str[16 * new.index(t): 16 * new.index(t) + 16] if t in new else blank for t in old),
                        pd.Series("", index=sub.index))
    return out.tolist()


def _lacking_types(codes: dict, header_fields, fields, version: float) -> str:
    """The types lfgnss reads (pseudorange, C/N0, Doppler and RINEX 2's stand-in code) of the constellations in
    ``codes`` that redefined ``fields`` lack, as "C1C S1C of G, S1 of GR" ("" if none)."""
    lacking: dict[str, str] = {}                # the types gone -> the constellations (letters) they are gone for
    for system, (*columns, _, i_fallback, _) in codes.items():
        old = header_fields if version < 3 else header_fields[system]
        new = fields if version < 3 else fields[system]
        gone = " ".join(old[i] for i in (*columns, i_fallback) if i >= 0 and old[i] not in new)
        if gone:
            lacking[gone] = lacking.get(gone, "") + system
    return ", ".join(f"{gone} of {systems}" for gone, systems in lacking.items())


def _numbers(texts: pd.Series) -> tuple[np.ndarray, np.ndarray]:
    """Float values of fixed-width fields (NaN where blank) and a mask of unreadable (garbage) fields."""
    import pandas as pd  # only when parsing: pandas costs ~0.4 s of start-up

    stripped = texts.str.strip()
    values = pd.to_numeric(stripped, errors="coerce").to_numpy(dtype=float)
    garbage = (stripped.str.len() > 0).to_numpy() & ~np.isfinite(values)
    return values, garbage


def _pseudoranges(texts: pd.Series) -> tuple[np.ndarray, np.ndarray]:
    """``_numbers`` of pseudorange fields [m], 0.000 read as missing (NaN), as RTKLIB reads it."""
    values, garbage = _numbers(texts)
    return np.where(values == 0.0, np.nan, values), garbage


_TIME_TOL_S = 1e-6


def _increasing_epochs(times: np.ndarray) -> np.ndarray:
    """(T,) bool: the longest strictly increasing run of epoch times, preferring the earliest epochs.

    Dropping the fewest epochs means one bad time stamp (a duplicate, a step back, or a jump far ahead)
    costs that epoch only, never the epochs after it; earlier epochs are kept on ties, so damage later
    in a file never removes epochs before it.
    """
    import bisect

    n = times.size
    longest = np.zeros(n, int)   # longest increasing run starting at each epoch (patience sorting, backwards)
    tails: list[float] = []      # tails[k]: largest start of a run of length k + 1 (negated: ascending)
    for i in range(n - 1, -1, -1):
        x = -times[i]
        pos = bisect.bisect_left(tails, x - _TIME_TOL_S)
        longest[i] = pos + 1
        if pos == len(tails):
            tails.append(x)
        elif x < tails[pos]:
            tails[pos] = x
    keep = np.zeros(n, bool)
    need, last = (int(longest.max()) if n else 0), -np.inf
    for i in range(n):
        if need and longest[i] == need and times[i] > last + _TIME_TOL_S:
            keep[i], last, need = True, times[i], need - 1
    return keep


def _gpst_text(t: float) -> str:
    return (_GPS_EPOCH + dt.timedelta(seconds=float(t))).isoformat(" ", "milliseconds") + " GPST"


def _assemble(path, info, codes, epoch_times, epoch_lines, rec_epoch, rec_sv, rec_text, rec_line,
              problems) -> Observations:
    import pandas as pd

    times = np.asarray(epoch_times, dtype=float)
    keep_epoch = _increasing_epochs(times)
    kept = np.flatnonzero(keep_epoch)
    for k in np.flatnonzero(~keep_epoch):  # duplicates, backward steps and time stamps out of order
        i = np.searchsorted(kept, k)
        prev = times[kept[i - 1]] if i > 0 else None
        if prev is not None and times[k] <= prev + _TIME_TOL_S:
            what = "repeats" if abs(times[k] - prev) <= _TIME_TOL_S else "is before"
            why = f"{what} the previous epoch {_gpst_text(prev)} (duplicate or time going backwards)"
        else:
            why = f"is after the next epoch {_gpst_text(times[kept[i]])} (time stamp out of order)"
        problems.append(f"{path}:{epoch_lines[k]}: epoch {_gpst_text(times[k])} {why}, skipped")
    raw_sv = pd.Series(rec_sv, dtype=object)
    sv = raw_sv.str.replace(" ", "0")
    system = sv.str[0]
    text = pd.Series(rec_text, dtype=object)
    epoch = np.asarray(rec_epoch, dtype=int)
    line = np.asarray(rec_line, dtype=int)
    valid_sv = (raw_sv.str.match(_SV_RE.pattern) & (sv.str[1:] != "00")).to_numpy() if len(sv) else np.zeros(0, bool)
    n_rec = len(sv)
    pr = np.full(n_rec, np.nan)
    cn0 = np.full(n_rec, np.nan)
    dop = np.full(n_rec, np.nan)
    bad = ~valid_sv
    unreadable_opt = np.zeros(n_rec, int)   # unreadable C/N0 and Doppler values per record (read as missing)
    opt_names: set[str] = set()
    for k in np.flatnonzero(~valid_sv):
        problems.append(f"{path}:{line[k]}: unreadable satellite id {rec_sv[k]!r}, record skipped")
    if info["version"] >= 3 and n_rec:
        for letter in SYSTEMS:  # supported constellation observed but absent from the header
            rows = np.flatnonzero((system == letter).to_numpy() & valid_sv & keep_epoch[epoch])
            if rows.size and letter not in info["fields"]:
                problems.append(f"{path}:{line[rows[0]]}: {rows.size} {letter} record(s) but no SYS / # / OBS TYPES "
                                f"header line for {letter}: skipped")
    for sys_letter, (i_pr, i_cn0, i_dop, code, i_fallback, fallback) in codes.items():
        rows = np.flatnonzero((system == sys_letter).to_numpy() & valid_sv)
        if rows.size == 0:
            continue
        sub = text.iloc[rows]
        for col, out, required in ((i_pr, pr, True), (i_cn0, cn0, False), (i_dop, dop, False)):
            if col < 0:
                continue
            values, garbage = (_pseudoranges if required else _numbers)(sub.str[16 * col: 16 * col + 14])
            out[rows] = values
            if required:
                for k in rows[garbage]:
                    problems.append(f"{path}:{line[k]}: unreadable pseudorange for {sv.iloc[k]}, record skipped")
                bad[rows[garbage]] = True
            elif garbage.any():
                out[rows[garbage]] = np.nan
                unreadable_opt[rows[garbage]] += 1
                opt_names.add(info["fields"][col] if info["version"] < 3 else info["fields"][sys_letter][col])
        blank = rows[np.isnan(pr[rows]) & ~bad[rows]] if i_fallback >= 0 else rows[:0]
        if blank.size:  # RINEX 2: the preferred code blank, the other one there (RTKLIB does the same)
            values, garbage = _pseudoranges(text.iloc[blank].str[16 * i_fallback: 16 * i_fallback + 14])
            for k in blank[garbage]:
                problems.append(f"{path}:{line[k]}: unreadable pseudorange {fallback} for {sv.iloc[k]} "
                                f"({code} blank), record skipped")
            bad[blank[garbage]] = True
            pr[blank] = values
            used = blank[np.isfinite(values) & keep_epoch[epoch[blank]]]
            if used.size:
                names = sorted(set(sv.iloc[used]))
                problems.append(f"{path}:{line[used[0]]}: {code} blank (or 0), {fallback} used instead in {used.size} "
                                f"record(s) of {len(names)} satellite(s) ({' '.join(names[:8])}"
                                f"{' ...' if len(names) > 8 else ''}); {fallback} differs from {code} by the "
                                f"satellite's {fallback}-{code} code bias (typically decimetres), not corrected")
    use = ~bad & system.isin(list(codes)).to_numpy() & np.isfinite(pr) & keep_epoch[epoch] if n_rec else np.zeros(0, bool)
    lost = np.flatnonzero(unreadable_opt * use)
    if lost.size:
        count = int(unreadable_opt[lost].sum())
        problems.append(f"{path}:{line[lost[0]]}: {count} unreadable C/N0 or Doppler value{'s' * (count > 1)} "
                        f"({'/'.join(sorted(opt_names))}; first here) read as missing")
    if use.any():
        _drop_repeated_satellites(path, use, epoch, sv, pr, line, problems)
    order = {s: i for i, s in enumerate(SYSTEMS)}
    svs = sorted(set(sv[use]), key=lambda s: (order.get(s[0], 99), s))
    col_of = {s: i for i, s in enumerate(svs)}
    new_epoch = np.cumsum(keep_epoch) - 1
    n_t, n_s = int(keep_epoch.sum()), len(svs)
    arrays = [np.full((n_t, n_s), np.nan) for _ in range(3)]
    r = new_epoch[epoch[use]]
    c = np.array([col_of[s] for s in sv[use]], dtype=int)
    for arr, vals in zip(arrays, (pr, cn0, dop)):
        arr[r, c] = vals[use]
    if n_t == 0:
        raise RinexError(path, "no usable observation epoch" + (f" ({problems[0]})" if problems else ""))
    return Observations(str(path), info["version"], times[keep_epoch], np.array(svs, dtype="<U3"), arrays[0],
                        arrays[1], arrays[2], {k: v[3] for k, v in codes.items() if any(s[0] == k for s in svs)},
                        info["approx"], tuple(problems))


def _drop_repeated_satellites(path, use, epoch, sv, pr, line, problems) -> None:
    """Clear ``use`` for repeated records of a satellite within one epoch, with one note per kind.

    A repeat with the same pseudorange is ignored (the first record is kept). Where the pseudoranges differ,
    every record of that satellite in that epoch is skipped rather than the first one kept: nothing tells
    which one is the satellite's (in RINEX 2, a damaged id list assigns another satellite's record), and
    one wrong pseudorange costs far more than one satellite less (a +5 km repeat kept gave 1 km errors).
    """
    import pandas as pd

    rows = np.flatnonzero(use)
    sv_code = pd.factorize(sv.iloc[rows])[0]
    key = epoch[rows].astype(np.int64) * (int(sv_code.max()) + 1) + sv_code
    order = np.argsort(key, kind="stable")        # records of one (epoch, satellite) together, in file order
    ks = key[order]
    starts = np.r_[True, ks[1:] != ks[:-1]]
    if starts.all():
        return
    first = np.empty(rows.size, int)
    first[order] = order[np.flatnonzero(starts)][np.cumsum(starts) - 1]   # the first record of each one's group
    repeat = first != np.arange(rows.size)
    differs = repeat & (pr[rows] != pr[rows[first]])
    drop = np.isin(key, key[differs])             # every record of a satellite-epoch whose pseudoranges differ
    same = repeat & ~drop
    if same.any():
        j, n = np.flatnonzero(same)[0], int(same.sum())
        problems.append(f"{path}:{line[rows[j]]}: satellite {sv.iloc[rows[j]]} listed twice in one epoch; the repeat "
                        f"is ignored" + (f" ({n} such repeated records in the file, first here)" if n > 1 else ""))
    if differs.any():
        j, n = np.flatnonzero(differs)[0], int(np.unique(key[differs]).size)
        problems.append(f"{path}:{line[rows[j]]}: satellite {sv.iloc[rows[j]]} listed twice in one epoch with "
                        f"different pseudoranges ({pr[rows[first[j]]]:.3f} m on line {line[rows[first[j]]]}, "
                        f"{pr[rows[j]]:.3f} m here): both records skipped"
                        + (f" ({n} such satellite-epochs in the file, first here)" if n > 1 else ""))
    use[rows[repeat | drop]] = False


def _first_redefinition(body: list[str], n_header: int, info: dict, path: Path) -> int | None:
    """Line number of the first event that gives observation types other than the header's, or None."""
    label_lines = [i for i, ln in enumerate(body) if ln[60:].strip().startswith(_TYPES_LABELS)]
    runs: list[list[int]] = []                  # one event's lines together
    for i in label_lines:
        if runs and i == runs[-1][-1] + 1:
            runs[-1].append(i)
        else:
            runs.append([i])
    for run in runs:
        if _types_redefined([body[i] for i in run], info, path, n_header + run[0] + 1, []) is not None:
            event = next((j for j in range(run[0] - 1, -1, -1) if body[j].startswith(">")
                          or _V2_EVENT_RE.match(body[j]) or _V2_EPOCH_RE.match(body[j])), run[0])
            return n_header + event + 1            # the event's line, as the lfgnss engine's notes name it
    return None


def _parse_georinex(text, path, info, codes, problems, redefined: int | None) -> Observations:
    import georinex

    if redefined is not None:   # georinex reads the header's columns throughout: the later values would be others
        raise RinexError(path, "an event redefines the observation types here, which engine='georinex' cannot read "
                               "(it would read other columns as pseudoranges); engine='lfgnss' reads them (or says "
                               "why not)",
                         line=redefined)
    meas = sorted({info["fields"][i] if info["version"] < 3 else info["fields"][s][i]
                   for s, idx in codes.items() for i in (*idx[:3], idx[4]) if i >= 0})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            ds = georinex.load(io.StringIO(text), use=list(codes), meas=meas)
        except Exception as err:
            raise RinexError(path, f"georinex could not read the file ({type(err).__name__}: {err})") from None
    times = tags_to_gps_s(ds.time.values, info["time_system"])
    svs = [str(s) for s in ds.sv.values if str(s)[0] in codes]
    order = {s: i for i, s in enumerate(SYSTEMS)}
    svs = sorted(svs, key=lambda s: (order.get(s[0], 99), s))

    def grab(which: int) -> np.ndarray:
        out = np.full((times.size, len(svs)), np.nan)
        for j, s in enumerate(svs):
            i = codes[s[0]][which]
            if i < 0:
                continue
            name = info["fields"][i] if info["version"] < 3 else info["fields"][s[0]][i]
            if name in ds:
                out[:, j] = ds[name].sel(sv=s).values
        return out

    pr, fallback = (np.where(a == 0.0, np.nan, a) for a in (grab(0), grab(4)))     # 0.000: missing
    pr = np.where(np.isnan(pr), fallback, pr)
    cn0, dop = grab(1), grab(2)                 # before svs is cut to the satellites kept: grab reads it
    keep = np.any(np.isfinite(pr), axis=0)
    svs = np.array(svs, dtype="<U3")[keep]
    return Observations(str(path), info["version"], times, svs, pr[:, keep], cn0[:, keep], dop[:, keep],
                        {k: v[3] for k, v in codes.items()}, info["approx"], tuple(problems))


def _to_npz(target: Path, obs: Observations) -> None:
    meta = json.dumps({"version": obs.version, "codes": obs.codes, "warnings": list(obs.warnings),
                       "path": str(obs.path)})
    np.savez(target, time_gps_s=obs.time_gps_s, sv=obs.sv, pr_m=obs.pr_m, cn0_dbhz=obs.cn0_dbhz,
             doppler_hz=obs.doppler_hz, approx_ecef_m=obs.approx_ecef_m, meta=np.array(meta))


def _from_npz(source: Path, path: Path) -> Observations:
    with np.load(source, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"]))
        old = meta["path"]  # the same content may have been parsed under another name: name this file
        notes = tuple(str(path) + w[len(old):] if w.startswith(old) else w for w in meta["warnings"])
        return Observations(str(path), meta["version"], z["time_gps_s"], z["sv"], z["pr_m"], z["cn0_dbhz"],
                            z["doppler_hz"], meta["codes"], z["approx_ecef_m"], notes)
