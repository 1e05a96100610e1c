"""Damaged-input corpus for ``tests/test_damaged_inputs.py``, made from real data.

Every file is cut from the bundled smartLoc Berlin Potsdamer Platz sample (RINEX 2.11 u-blox
observations, CDDIS GPS/GLONASS broadcast navigation, smartLoc ground truth; CC BY-SA 4.0): a few dozen
epochs, nav records of a few hours, then one damage per case. Nothing is invented except the damage.
The cases and their documented behaviour are listed in ``CASES`` and in ``docs/bad_input.md``.

Usage::

    python tests/corpus/make_corpus.py [OUT_DIR]      # default: tests/corpus/files

The tests call :func:`build` into a temporary folder, so nothing has to be committed; the command
writes the same files for people who want to feed them to ``python -m lfgnss.solve`` by hand.
"""
from __future__ import annotations

import gzip
import json
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

SAMPLE = Path(__file__).resolve().parents[2] / "lfgnss" / "data" / "berlin-potsdamer-platz"
SAMPLE_OBS = SAMPLE / "Berlin_Potsdamer_Platz.obs.gz"
SAMPLE_GPS_NAV = SAMPLE / "brdc1580.16n.gz"
SAMPLE_GLO_NAV = SAMPLE / "brdc1580.16g.gz"
SAMPLE_TRUTH = SAMPLE / "Berlin_Potsdamer_Platz_GT.txt"

#: Epochs of the base observation file (5 Hz: 5.8 s of driving).
BASE_EPOCHS = 30
_V2_EPOCH_RE = re.compile(r"^ [ \d]\d [ \d]\d [ \d]\d [ \d]\d [ \d]\d [ \d]\d\.\d+ +[0-6][ \d]{3}")
_NAV2_START = re.compile(r"^[ 0-9][0-9] [ 0-9][0-9] [ 0-9][0-9] [ 0-9][0-9] ")


# ------------------------------------------------------------------------------------------- real data
def _text(path: Path) -> str:
    raw = path.read_bytes()
    if raw[:2] == b"\x1f\x8b":
        raw = gzip.decompress(raw)
    return raw.decode("ascii")


@dataclass
class ObsV2:
    """A RINEX 2.11 observation file as header lines and, per epoch, its lines (epoch line(s) + records)."""

    header: list[str]
    epochs: list[list[str]]

    @classmethod
    def parse(cls, text: str) -> "ObsV2":
        lines = text.splitlines()
        end = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1
        n_types = int(next(ln for ln in lines[:end] if "# / TYPES OF OBSERV" in ln)[:6])
        per_sat = (n_types + 4) // 5
        epochs, i = [], end
        while i < len(lines):
            if not _V2_EPOCH_RE.match(lines[i]):
                i += 1
                continue
            nsat = int(lines[i][29:32])
            n = (nsat + 11) // 12 + nsat * per_sat
            epochs.append(lines[i: i + n])
            i += n
        return cls(lines[:end], epochs)

    def copy(self) -> "ObsV2":
        return ObsV2(list(self.header), [list(e) for e in self.epochs])

    def text(self, newline: str = "\n") -> str:
        return newline.join(self.header + [ln for ep in self.epochs for ln in ep]) + newline

    def line_of(self, epoch: int, offset: int = 0) -> int:
        """1-based line number of line ``offset`` of epoch ``epoch`` in :meth:`text`."""
        return len(self.header) + sum(len(e) for e in self.epochs[:epoch]) + offset + 1

    @staticmethod
    def n_sv_lines(epoch: list[str]) -> int:
        return (int(epoch[0][29:32]) + 11) // 12

    @staticmethod
    def svs(epoch: list[str]) -> list[str]:
        n = int(epoch[0][29:32])
        ids = "".join(ln[32:68] for ln in epoch[: (n + 11) // 12])
        return [ids[3 * k: 3 * k + 3] for k in range(n)]

    def record(self, epoch: int, sv: str) -> int:
        """Offset (within the epoch) of the record line of satellite ``sv``."""
        ep = self.epochs[epoch]
        return self.n_sv_lines(ep) + self.svs(ep).index(sv)


def base_obs(n_epochs: int = BASE_EPOCHS, start: int = 0) -> ObsV2:
    """Epochs ``start .. start + n_epochs`` of the bundled Berlin RINEX 2.11 file."""
    full = ObsV2.parse(_text(SAMPLE_OBS))
    return ObsV2(full.header, full.epochs[start: start + n_epochs])


def full_obs() -> ObsV2:
    return ObsV2.parse(_text(SAMPLE_OBS))


def set_field(line: str, index: int, value: str) -> str:
    """Line with the 16-column observation field ``index`` (F14.3 + LLI + SSI) set to ``value`` (14 wide)."""
    line = line.ljust(80)
    return (line[: 16 * index] + value.rjust(14)[:14] + line[16 * index + 14:]).rstrip()


def to_v3(obs: ObsV2, version: str = "3.03") -> tuple[str, int]:
    """The same data as RINEX 3 (types C1C L1C S1C D1C, same field columns); returns (text, header lines)."""
    types = {"G": "C1C L1C S1C D1C", "R": "C1C L1C S1C D1C", "S": "C1C L1C S1C D1C"}
    head = [f"{version:>9s}           OBSERVATION DATA    M                   RINEX VERSION / TYPE",
            "make_corpus.py      lfgnss tests        20240101 000000 UTC PGM / RUN BY / DATE"]
    head += [f"{s}    4 {t}".ljust(60) + "SYS / # / OBS TYPES" for s, t in types.items()]
    head += [ln for ln in obs.header if "TIME OF FIRST OBS" in ln]
    head += [" " * 60 + "END OF HEADER"]
    body = []
    for ep in obs.epochs:
        e = ep[0]
        yy, mo, d, h, mi, s = int(e[1:3]), int(e[4:6]), int(e[7:9]), int(e[10:12]), int(e[13:15]), float(e[15:26])
        svs = [("G" + sv[1:]) if sv[0] == " " else sv for sv in ObsV2.svs(ep)]
        body.append(f"> {2000 + yy:4d} {mo:02d} {d:02d} {h:02d} {mi:02d}{s:11.7f}  {int(e[28])}{len(svs):3d}")
        for sv, rec in zip(svs, ep[ObsV2.n_sv_lines(ep):]):
            body.append(sv + rec)
    return "\n".join(head + body) + "\n", len(head)


def _nav_records(text: str, lines_per_record: int) -> tuple[list[str], list[list[str]]]:
    lines = text.splitlines()
    end = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1
    body = lines[end:]
    recs = [body[i: i + lines_per_record] for i in range(0, len(body), lines_per_record)]
    assert all(_NAV2_START.match(r[0]) for r in recs)
    return lines[:end], recs


def _join(header: list[str], recs: list[list[str]]) -> str:
    return "\n".join(header + [ln for r in recs for ln in r]) + "\n"


def base_nav(kind: str, hours: tuple[int, int] | None = None) -> tuple[list[str], list[list[str]]]:
    """GPS (``"n"``, 8 lines per record) or GLONASS (``"g"``, 4) records with epoch hour in ``hours``."""
    path, per, default = (SAMPLE_GPS_NAV, 8, (9, 13)) if kind == "n" else (SAMPLE_GLO_NAV, 4, (10, 12))
    lo, hi = hours or default
    header, recs = _nav_records(_text(path), per)
    return header, [r for r in recs if lo <= int(r[0][12:14]) <= hi]


def set_nav_value(line: str, slot: int, value: float, first_line: bool) -> str:
    """Nav line with field ``slot`` (0..3 on continuation lines; 0..2 after the epoch on the first) replaced."""
    col = (22 if first_line else 3) + 19 * slot
    text = f"{value:19.12E}".replace("E", "D")
    return line[:col] + text + line[col + 19:]


def nav_value(line: str, slot: int, first_line: bool) -> float:
    col = (22 if first_line else 3) + 19 * slot
    return float(line[col: col + 19].replace("D", "E"))


def base_truth(n_epochs: int = BASE_EPOCHS) -> list[str]:
    return SAMPLE_TRUTH.read_text().splitlines()[:n_epochs]


def base_model(path: Path) -> Path:
    """A randomly initialised LF-GNSS network exported as a model file (format of ``learning.export``)."""
    import torch

    from learning.export import export_model
    from learning.network import LfgnssNet
    from learning.normalise import Normaliser
    from lfgnss.sequence import DEFAULT_FEATURES
    from lfgnss.simulate import simulate_sequence

    norm = Normaliser.fit([simulate_sequence(20, seed=5, n_slots=12)], DEFAULT_FEATURES)
    torch.manual_seed(0)
    net = LfgnssNet(len(DEFAULT_FEATURES), d_model=16, n_heads=2, hidden=(16, 16), r_floor_m2=1.0,
                    r_scale_m2=10.0, r_init_m2=25.0)
    ckpt = path.with_suffix(".pt")
    torch.save({"model": net.state_dict(), "model_hparams": net.hyperparameters(), "normaliser": norm.to_dict(),
                "config": {"seed": 0}, "epoch": 0, "history": []}, ckpt)
    try:
        return export_model(ckpt, path, extra_metadata={"created_utc": "2024-01-01T00:00:00+00:00",
                                                        "note": "tests/corpus: untrained network"})
    finally:
        ckpt.unlink()


# ------------------------------------------------------------------------------------------- cases
@dataclass(frozen=True)
class Case:
    """One damaged input and what lfgnss must do with it.

    outcome : ``"error"`` (one line ``error: FILE[:LINE]: reason``, exit code 2, no output),
              ``"warning"`` (exit 0, a warning line containing ``message``, the damage skipped and counted),
              ``"ok"`` (exit 0, result as for the clean file or with the damage counted in the qc summary).
    culprit : which input the message names: ``"obs"``, ``"nav"``, ``"truth"`` or ``"model"``.
    line : line number the message must name (``FILE:LINE``), if any.
    fault_epoch : index of the first damaged epoch of the base file; the EKF results of every earlier
              epoch must equal those of the clean file (None: the damage is not tied to an epoch).
    qc : a qc reason that the summary must count (e.g. ``"pseudorange out of range"``).
    """

    name: str
    damage: str
    outcome: str
    message: str
    behaviour: str
    obs: str = "base.obs"
    nav: tuple[str, ...] = ("base.16n", "base.16g")
    truth: str | None = None
    model: str | None = None
    culprit: str = "obs"
    line: int | None = None
    fault_epoch: int | None = None
    qc: str | None = None
    extra: dict = field(default_factory=dict)


_BUILDERS = []


def _case(fn):
    _BUILDERS.append(fn)
    return fn


def _write(out: Path, name: str, data: str | bytes) -> str:
    path = out / name
    if isinstance(data, str):
        data = data.encode("latin-1")
    path.write_bytes(data)
    return name


# --- observation file: whole-file damage
@_case
def obs_empty(out):
    return Case("obs_empty", "observation file of 0 bytes", "error", "file is empty",
                "error naming the file", obs=_write(out, "obs_empty.obs", b""))


@_case
def obs_blank(out):
    return Case("obs_blank", "observation file of blank lines only", "error", "file is empty",
                "error naming the file", obs=_write(out, "obs_blank.obs", "\n  \n\n"))


@_case
def obs_missing(out):
    return Case("obs_missing", "observation file does not exist", "error", "cannot read file",
                "error naming the file", obs="obs_does_not_exist.obs")


@_case
def obs_binary(out):
    data = SAMPLE_GPS_NAV.read_bytes()[40:4000]     # bytes of a gzip stream without its magic number
    return Case("obs_binary", "binary garbage (not RINEX at all)", "error", "END OF HEADER",
                "error naming the file", obs=_write(out, "obs_binary.obs", data))


@_case
def obs_truncated_header(out):
    text = base_obs().text()
    cut = text.index("# / TYPES OF OBSERV") - 30
    return Case("obs_truncated_header", "file cut inside the header", "error", "END OF HEADER",
                "error naming the file", obs=_write(out, "obs_truncated_header.obs", text[:cut]))


@_case
def obs_truncated(out):
    obs = base_obs()
    k = 20
    lines = obs.text().splitlines()
    n = obs.line_of(k, 8)                    # cut in the middle of the 8th record line of epoch 21
    text = "\n".join(lines[: n - 1]) + "\n" + lines[n - 1][:23]
    return Case("obs_truncated", "file cut in the middle of a record (epoch 21 of 30)", "warning",
                "epoch truncated", "warning; the incomplete last epoch is skipped, all earlier epochs are solved",
                obs=_write(out, "obs_truncated.obs", text), line=obs.line_of(k), fault_epoch=k)


@_case
def obs_truncated_gz(out):
    data = gzip.compress(base_obs().text().encode(), mtime=0)
    return Case("obs_truncated_gz", "gzip file cut short (interrupted download)", "warning",
                "compressed data end early",
                "warning; the epochs that could be decompressed are solved, the cut one is skipped",
                obs=_write(out, "obs_truncated_gz.obs.gz", data[: int(len(data) * 0.6)]), fault_epoch=12)


@_case
def obs_damaged_gz(out):
    data = bytearray(gzip.compress(base_obs().text().encode(), mtime=0))
    data[len(data) // 2] ^= 0x55                     # one damaged byte inside the deflate stream
    return Case("obs_damaged_gz", "gzip file with one damaged byte in the middle", "error", "damaged gzip data",
                "error naming the file: the damage may lie anywhere before zlib detects it, so no value is trusted",
                obs=_write(out, "obs_damaged_gz.obs.gz", bytes(data)))


@_case
def obs_crlf(out):
    return Case("obs_crlf", "CRLF (Windows) line endings", "ok", "",
                "read exactly as the LF file", obs=_write(out, "obs_crlf.obs", base_obs().text("\r\n")),
                fault_epoch=BASE_EPOCHS)


@_case
def obs_nav_as_obs(out):
    header, recs = base_nav("n")
    return Case("obs_nav_as_obs", "a navigation file given as the observation file", "error",
                "not an observation file", "error naming the file and line 1",
                obs=_write(out, "obs_nav_as_obs.obs", _join(header, recs[:4])), line=1)


# --- observation file: header damage
@_case
def obs_unknown_version(out):
    obs = base_obs()
    obs.header[0] = "     1.00" + obs.header[0][9:]
    return Case("obs_unknown_version", "RINEX VERSION / TYPE says version 1.00", "error",
                "unsupported RINEX version", "error naming the file and line 1",
                obs=_write(out, "obs_unknown_version.obs", obs.text()), line=1)


@_case
def obs_future_version(out):
    obs = base_obs()
    obs.header[0] = "     5.00" + obs.header[0][9:]
    return Case("obs_future_version", "RINEX VERSION / TYPE says version 5.00 (not yet defined)", "error",
                "unsupported RINEX version", "error naming the file and line 1",
                obs=_write(out, "obs_future_version.obs", obs.text()), line=1)


@_case
def obs_garbage_version(out):
    obs = base_obs()
    obs.header[0] = "     V2.x" + obs.header[0][9:]
    return Case("obs_garbage_version", "version field is not a number", "error", "version",
                "error naming the file and line 1",
                obs=_write(out, "obs_garbage_version.obs", obs.text()), line=1)


@_case
def obs_missing_version_line(out):
    obs = base_obs()
    obs.header = obs.header[1:]
    return Case("obs_missing_version_line", "header without its RINEX VERSION / TYPE line", "error",
                "RINEX VERSION / TYPE", "error naming the file and line 1",
                obs=_write(out, "obs_missing_version_line.obs", obs.text()), line=1)


@_case
def obs_missing_obs_types(out):
    obs = base_obs()
    obs.header = [ln for ln in obs.header if "# / TYPES OF OBSERV" not in ln]
    return Case("obs_missing_obs_types", "header without its # / TYPES OF OBSERV line", "error",
                "observation type", "error naming the file",
                obs=_write(out, "obs_missing_obs_types.obs", obs.text()))


@_case
def obs_no_code_type(out):
    obs = base_obs()
    obs.header = [ln.replace("    C1    L1", "    X1    L1") if "# / TYPES OF OBSERV" in ln else ln
                  for ln in obs.header]
    return Case("obs_no_code_type", "# / TYPES OF OBSERV lists no pseudorange (C1 renamed X1)", "error",
                "no pseudorange observation type", "error naming the file",
                obs=_write(out, "obs_no_code_type.obs", obs.text()))


@_case
def obs_wrong_type_count(out):
    obs = base_obs()
    obs.header = [("     9" + ln[6:]) if "# / TYPES OF OBSERV" in ln else ln for ln in obs.header]
    line = next(i for i, ln in enumerate(obs.header) if "# / TYPES OF OBSERV" in ln) + 1
    return Case("obs_wrong_type_count", "# / TYPES OF OBSERV says 9 types but lists and records 4", "error",
                "TYPES OF OBSERV", "error naming the file and the header line",
                obs=_write(out, "obs_wrong_type_count.obs", obs.text()), line=line)


@_case
def obs_no_time_of_first_obs(out):
    obs = base_obs()
    obs.header = [ln for ln in obs.header if "TIME OF FIRST OBS" not in ln]
    return Case("obs_no_time_of_first_obs", "header without TIME OF FIRST OBS", "ok", "",
                "read as GPS time, results as for the clean file",
                obs=_write(out, "obs_no_time_of_first_obs.obs", obs.text()), fault_epoch=BASE_EPOCHS)


# --- observation file: data-line damage
@_case
def obs_garbage_fields(out):
    obs = base_obs()
    k = 10
    off = obs.record(k, "G19")
    obs.epochs[k][off] = set_field(obs.epochs[k][off], 0, "19#84?89.6x2")
    off2 = obs.record(k + 1, "R02")
    obs.epochs[k + 1][off2] = set_field(obs.epochs[k + 1][off2], 0, "@@@@@@@@@@@@@@")
    return Case("obs_garbage_fields", "ASCII garbage in the pseudorange field of two records", "warning",
                "unreadable pseudorange", "warning naming file and line; those two records are skipped",
                obs=_write(out, "obs_garbage_fields.obs", obs.text()), line=obs.line_of(k, off), fault_epoch=k)


@_case
def obs_non_ascii(out):
    obs = base_obs()
    k = 12
    off = obs.record(k, "G12")
    line = obs.epochs[k][off]
    obs.epochs[k][off] = line[:4] + "\xff\xe9" + line[6:]            # 2 bytes replaced in the pseudorange
    off2 = obs.record(k, "G24")
    line = obs.epochs[k][off2]
    obs.epochs[k][off2] = line[:33] + "\xb0\xb0" + line[35:]         # 2 bytes in the C/N0 field
    return Case("obs_non_ascii", "non-ASCII bytes (0xFF 0xE9 0xB0) inside data fields", "warning",
                "unreadable pseudorange",
                "warning naming file and line; the record with a damaged pseudorange is skipped, the one with a "
                "damaged C/N0 is counted as 'no C/N0'",
                obs=_write(out, "obs_non_ascii.obs", obs.text()), line=obs.line_of(k, off), fault_epoch=k)


@_case
def obs_garbage_lines(out):
    obs = base_obs()
    k = 15
    junk = SAMPLE_GPS_NAV.read_bytes()[100:400].decode("latin-1").replace("\n", " ").replace("\r", " ")
    line = obs.line_of(k)
    obs.epochs[k - 1] = obs.epochs[k - 1] + [junk[:120], junk[120:]]
    return Case("obs_garbage_lines", "two lines of binary garbage between two epochs", "warning",
                "unreadable epoch line", "warning naming file and line; the garbage is skipped up to the next epoch",
                obs=_write(out, "obs_garbage_lines.obs", obs.text()), line=line,
                fault_epoch=BASE_EPOCHS)


@_case
def obs_bad_epoch_line(out):
    obs = base_obs()
    k = 18
    obs.epochs[k][0] = obs.epochs[k][0][:10] + "x:" + obs.epochs[k][0][12:]
    return Case("obs_bad_epoch_line", "unreadable time in an epoch line", "warning", "unreadable epoch line",
                "warning naming file and line; that epoch is skipped",
                obs=_write(out, "obs_bad_epoch_line.obs", obs.text()), line=obs.line_of(k), fault_epoch=k)


@_case
def obs_bad_sv_id(out):
    obs = base_obs()
    k = 20
    e = obs.epochs[k][0]
    obs.epochs[k][0] = e[:35] + "?1" + e[37:]                    # second satellite id of the epoch
    return Case("obs_bad_sv_id", "unreadable satellite id in an epoch line", "warning",
                "unreadable satellite id", "warning naming file and line; that record is skipped",
                obs=_write(out, "obs_bad_sv_id.obs", obs.text()), line=obs.line_of(k, 3), fault_epoch=k)


@_case
def obs_sat_count_too_high(out):
    obs = base_obs()
    k = 16
    e = obs.epochs[k][0]
    obs.epochs[k][0] = e[:29] + f"{int(e[29:32]) + 3:3d}" + e[32:]
    return Case("obs_sat_count_too_high", "epoch line announces 3 more satellites than it has", "warning",
                "epoch truncated", "warning naming file and line; that epoch is skipped",
                obs=_write(out, "obs_sat_count_too_high.obs", obs.text()), line=obs.line_of(k), fault_epoch=k)


def _keep_satellites(obs: ObsV2, k: int, keep: set[str]) -> None:
    ep = obs.epochs[k]
    svs = ObsV2.svs(ep)
    recs = [r for sv, r in zip(svs, ep[ObsV2.n_sv_lines(ep):]) if sv in keep]
    ids = "".join(sv for sv in svs if sv in keep)
    head = ep[0][:29] + f"{len(recs):3d}" + ids[:36]
    obs.epochs[k] = [head] + ([" " * 32 + ids[36:]] if len(ids) > 36 else []) + recs


@_case
def obs_too_few_satellites(out):
    obs = base_obs()
    for k in range(BASE_EPOCHS):
        _keep_satellites(obs, k, {"G12", "G19", "G24"})
    return Case("obs_too_few_satellites", "3 satellites in every epoch (no fix possible)", "error",
                "no epoch has a coarse fix", "error naming the file (the API error names no file: see docs)",
                obs=_write(out, "obs_too_few_satellites.obs", obs.text()), extra={"api_no_file": True})


@_case
def obs_few_satellites_some_epochs(out):
    obs = base_obs()
    for k in range(12, 18):
        _keep_satellites(obs, k, {"G12", "G19", "G24"})
    return Case("obs_few_satellites_some_epochs", "only 3 satellites in 6 epochs", "ok", "",
                "solved; those epochs have no coarse fix ('too few satellites' in the summary) and the estimators "
                "carry the solution through them", obs=_write(out, "obs_few_satellites_some_epochs.obs", obs.text()),
                fault_epoch=12)


@_case
def obs_repeated_record_line(out):
    obs = base_obs()
    k = 14
    off = obs.record(k, "G19")
    obs.epochs[k].insert(off + 1, obs.epochs[k][off])              # G19's record line written twice
    return Case("obs_repeated_record_line", "one record line written twice inside an epoch (RINEX 2)", "warning",
                "records cannot be matched to satellites",
                "warning naming file and line; that epoch is skipped, since every record after the repeat would "
                "go to the wrong satellite", obs=_write(out, "obs_repeated_record_line.obs", obs.text()),
                line=obs.line_of(k), fault_epoch=k)


@_case
def obs_duplicate_epoch(out):
    obs = base_obs()
    k = 10
    obs.epochs.insert(k + 1, list(obs.epochs[k]))
    return Case("obs_duplicate_epoch", "one epoch written twice", "warning", "duplicate or time going backwards",
                "warning naming file and line; the repeated epoch is skipped",
                obs=_write(out, "obs_duplicate_epoch.obs", obs.text()), line=obs.line_of(k + 1),
                fault_epoch=BASE_EPOCHS)


@_case
def obs_time_backwards(out):
    obs = base_obs()
    k = 20
    e = obs.epochs[k][0]
    obs.epochs[k][0] = e[:13] + "09" + e[15:]                     # 11:10:45.7 -> 11:09:45.7
    return Case("obs_time_backwards", "an epoch time stamp one minute before the previous one", "warning",
                "duplicate or time going backwards", "warning naming file and line; that epoch is skipped",
                obs=_write(out, "obs_time_backwards.obs", obs.text()), line=obs.line_of(k), fault_epoch=k)


@_case
def obs_time_jump_forward(out):
    obs = base_obs()
    e = obs.epochs[0][0]
    obs.epochs[0][0] = e[:10] + "13" + e[12:]                     # 11:10:41.7 -> 13:10:41.7
    return Case("obs_time_jump_forward", "the first epoch time stamped two hours late", "warning",
                "time stamp out of order",
                "warning naming file and line; that epoch is skipped (not the 29 after it), so no position is "
                "computed at a wrong time", obs=_write(out, "obs_time_jump_forward.obs", obs.text()),
                line=obs.line_of(0))


@_case
def obs_gap(out):
    full = full_obs()
    obs = ObsV2(full.header, full.epochs[:15] + full.epochs[1000:1015])
    return Case("obs_gap", "a gap of 3.3 minutes without epochs (epochs 1..15, then 1001..1015)", "ok", "",
                "solved; the EKF restarts from the coarse fix after the gap (status reset)",
                obs=_write(out, "obs_gap.obs", obs.text()), fault_epoch=15, extra={"reset_at": 15})


@_case
def obs_empty_epochs(out):
    full = full_obs()
    empty = [[ep[0][:29] + "  0"] for ep in full.epochs[15:315]]     # the real epoch times, no satellite
    obs = ObsV2(full.header, full.epochs[:15] + empty + full.epochs[315:330])
    return Case("obs_empty_epochs", "60 s of epochs without any satellite (a tunnel) between two 3 s stretches",
                "ok", "", "solved; the empty epochs are coasted (Q=7 in .pos, 'coasted' in CSV), the filter "
                "updates again after the tunnel", obs=_write(out, "obs_empty_epochs.obs", obs.text()),
                fault_epoch=15, extra={"tunnel": (15, 315)})


@_case
def obs_pr_zero_and_huge(out):
    obs = base_obs()
    for k in range(10, 15):
        off = obs.record(k, "G12")
        obs.epochs[k][off] = set_field(obs.epochs[k][off], 0, "0.000")
        off = obs.record(k, "G19")
        obs.epochs[k][off] = set_field(obs.epochs[k][off], 0, "1000000000.000")
    return Case("obs_pr_zero_and_huge", "pseudoranges of 0 m (G12) and 1e9 m (G19) in 5 epochs", "ok", "",
                "solved without those observations, counted as 'pseudorange out of range'",
                obs=_write(out, "obs_pr_zero_and_huge.obs", obs.text()), fault_epoch=10,
                qc="pseudorange out of range")


@_case
def obs_pr_offset(out):
    obs = base_obs()
    for k in range(BASE_EPOCHS):
        off = obs.record(k, "G24")
        pr = float(obs.epochs[k][off][:14])
        obs.epochs[k][off] = set_field(obs.epochs[k][off], 0, f"{pr + 150000.0:.3f}")
    return Case("obs_pr_offset", "one satellite (G24) with pseudoranges 150 km too long in every epoch", "ok", "",
                "solved without it: the coarse fix drops it as a gross residual, counted",
                obs=_write(out, "obs_pr_offset.obs", obs.text()), qc="gross residual")


@_case
def obs_no_cn0(out):
    obs = base_obs()
    obs.header = ["     3    C1    L1    D1".ljust(60) + ln[60:] if "# / TYPES OF OBSERV" in ln else ln
                  for ln in obs.header]
    for ep in obs.epochs:
        for j in range(ObsV2.n_sv_lines(ep), len(ep)):
            ep[j] = (ep[j].ljust(64)[:32] + ep[j].ljust(64)[48:64]).rstrip()
    return Case("obs_no_cn0", "no C/N0 at all (S1 not recorded)", "warning", "no C/N0",
                "warning; C/N0 assumed 40 dB-Hz for every observation",
                obs=_write(out, "obs_no_cn0.obs", obs.text()))


@_case
def obs_zero_cn0(out):
    obs = base_obs()
    for ep in obs.epochs:
        for j in range(ObsV2.n_sv_lines(ep), len(ep)):
            ep[j] = set_field(ep[j], 2, "0.000")
    return Case("obs_zero_cn0", "every C/N0 written as 0.000 (converter's 'not recorded')", "warning", "no C/N0",
                "warning; C/N0 assumed 40 dB-Hz for every observation",
                obs=_write(out, "obs_zero_cn0.obs", obs.text()))


@_case
def obs_blank_cn0(out):
    obs = base_obs()
    for k in range(5, BASE_EPOCHS):
        off = obs.record(k, "G02")
        obs.epochs[k][off] = set_field(obs.epochs[k][off], 2, "")
    return Case("obs_blank_cn0", "C/N0 field blank for one satellite (G02) from epoch 6 on", "ok", "",
                "solved without it, counted as 'no C/N0'", obs=_write(out, "obs_blank_cn0.obs", obs.text()),
                fault_epoch=5, qc="no C/N0")


@_case
def obs_absurd_cn0(out):
    obs = base_obs()
    k = 8
    for sv, value in (("G12", "99999999999.99"), ("G19", "-50.000"), ("R20", "nan")):
        off = obs.record(k, sv)
        obs.epochs[k][off] = set_field(obs.epochs[k][off], 2, value)
    return Case("obs_absurd_cn0", "C/N0 of 1e11, -50 and 'nan' dB-Hz in one epoch", "ok", "",
                "solved without those observations, counted as 'no C/N0' (outside 0 to 100 dB-Hz or unreadable)",
                obs=_write(out, "obs_absurd_cn0.obs", obs.text()), fault_epoch=k, qc="no C/N0")


@_case
def obs_v3_truncated(out):
    obs = base_obs()
    text, n_head = to_v3(obs)
    lines = text.splitlines()
    k = 24
    start = n_head + sum(1 + len(ObsV2.svs(e)) for e in obs.epochs[:k])  # 0-based index of epoch k's line
    cut = "\n".join(lines[: start + 6])
    return Case("obs_v3_truncated", "RINEX 3.03 file cut after the 5th record of epoch 25", "warning",
                "epoch truncated", "warning naming file and line; earlier epochs are solved",
                obs=_write(out, "obs_v3_truncated.rnx", cut), line=start + 1, fault_epoch=k)


@_case
def obs_v3_missing_system(out):
    text, _ = to_v3(base_obs())
    text = "\n".join(ln for ln in text.split("\n") if not (ln.startswith("R ") and "SYS / # / OBS TYPES" in ln))
    return Case("obs_v3_missing_system", "RINEX 3 header without the GLONASS SYS / # / OBS TYPES line", "warning",
                "no SYS / # / OBS TYPES header line for R", "warning; the GLONASS records are skipped, GPS is solved",
                obs=_write(out, "obs_v3_missing_system.rnx", text))


# --- navigation files
def _gps_nav_with(out, name, change) -> str:
    header, recs = base_nav("n")
    for r in recs:
        if int(r[0][:2]) == 12:
            change(r)
    return _write(out, name, _join(header, recs))


@_case
def nav_wrong_clock(out):
    def change(r):
        r[0] = set_nav_value(r[0], 0, nav_value(r[0], 0, True) + 1e-3, True)   # af0 + 1 ms: 300 km
    name = _gps_nav_with(out, "nav_wrong_clock.16n", change)
    return Case("nav_wrong_clock", "broadcast clock of G12 off by 1 ms (300 km)", "ok", "",
                "solved without G12: the coarse fix drops it as a gross residual, counted",
                nav=(name, "base.16g"), culprit="nav", qc="gross residual")


@_case
def nav_unhealthy(out):
    def change(r):
        r[6] = set_nav_value(r[6], 1, 63.0, False)                           # SV health word
    name = _gps_nav_with(out, "nav_unhealthy.16n", change)
    return Case("nav_unhealthy", "G12 flagged unhealthy in its ephemerides", "ok", "",
                "solved without G12, counted as 'unhealthy'", nav=(name, "base.16g"), culprit="nav",
                qc="unhealthy")


@_case
def nav_other_day(out):
    days = 2
    header, recs = base_nav("n")
    for r in recs:
        r[0] = r[0][:9] + f"{int(r[0][9:11]) + days:2d}" + r[0][11:]
        r[3] = set_nav_value(r[3], 0, nav_value(r[3], 0, False) + days * 86400.0, False)   # toe
        r[7] = set_nav_value(r[7], 0, nav_value(r[7], 0, False) + days * 86400.0, False)   # transmission time
    gps = _write(out, "nav_other_day.16n", _join(header, recs))
    header, recs = base_nav("g")
    for r in recs:
        r[0] = r[0][:9] + f"{int(r[0][9:11]) + days:2d}" + r[0][11:]
    glo = _write(out, "nav_other_day.16g", _join(header, recs))
    return Case("nav_other_day", "navigation files of 2016-06-08, observations of 2016-06-06", "error",
                "no ephemeris", "error naming the files: no satellite has an ephemeris for the epochs",
                nav=(gps, glo), culprit="nav")


@_case
def nav_gps_only(out):
    return Case("nav_gps_only", "no GLONASS navigation file (GLONASS observed)", "warning", "no usable R observation",
                "warning; GLONASS counted as 'no ephemeris', solved with GPS", nav=("base.16n",), culprit="nav",
                qc="no ephemeris")


@_case
def nav_empty(out):
    return Case("nav_empty", "empty navigation file", "error", "empty", "error naming the file",
                nav=(_write(out, "nav_empty.16n", b""), "base.16g"), culprit="nav")


@_case
def nav_truncated(out):
    header, recs = base_nav("n")
    text = _join(header, recs)
    cut = text[: text.rindex("\n", 0, len(text) - 300) - 10]        # inside the last record
    return Case("nav_truncated", "GPS navigation file cut inside its last record", "warning", "record cut short",
                "warning naming the file and line; the incomplete record is skipped, solved with the others",
                nav=(_write(out, "nav_truncated.16n", cut), "base.16g"), culprit="nav", line=617,
                fault_epoch=BASE_EPOCHS)


@_case
def nav_garbage(out):
    header, recs = base_nav("n")
    recs[3][2] = recs[3][2][:10] + "##garbage##" + recs[3][2][21:]
    return Case("nav_garbage", "garbage inside one ephemeris record", "warning", "unreadable value",
                "warning naming the file and line; that one record is skipped, solved with the others",
                nav=(_write(out, "nav_garbage.16n", _join(header, recs)), "base.16g"), culprit="nav", line=35)


@_case
def nav_obs_as_nav(out):
    return Case("nav_obs_as_nav", "an observation file given as navigation file", "error", "navigation",
                "error naming the file", nav=("base.obs",), culprit="nav")


# --- ground truth
@_case
def truth_bad_lines(out):
    lines = base_truth()
    lines[3] = "point3 0.7 3785105.1 899901.9 garbage 0 0 0 0 0 0 0 0 0"
    lines[7] = "point3 1.5 3785103.2"
    lines[11] = "point3 2.3 nan 899902.4 5037238.9 0 0 0 0 0 0 0 0 0"
    lines[15] = "point3 3.1 3785100\xe9.0 899902.7 5037240.1 0 0 0 0 0 0 0 0 0"
    return Case("truth_bad_lines", "ground truth with 4 bad lines (text, short, NaN, non-ASCII)", "warning",
                "unreadable truth line", "warning per bad line naming file and line; those epochs are unlabelled",
                truth=_write(out, "truth_bad_lines.txt", "\n".join(lines) + "\n"), culprit="truth", line=4)


@_case
def truth_all_bad(out):
    lines = [ln.replace("point3", "point3 x") for ln in base_truth()]
    return Case("truth_all_bad", "ground truth without a single readable line", "error",
                "no readable ground-truth line",
                "error naming the file", truth=_write(out, "truth_all_bad.txt", "\n".join(lines) + "\n"),
                culprit="truth")


@_case
def truth_missing(out):
    return Case("truth_missing", "ground-truth file does not exist", "error", "cannot read truth file",
                "error naming the file", truth="truth_does_not_exist.txt", culprit="truth")


# --- model file
def _model_bytes(out) -> bytes:
    path = out / "model_ok.npz"
    if not path.exists():
        base_model(path)
    return path.read_bytes()


@_case
def model_truncated(out):
    data = _model_bytes(out)
    return Case("model_truncated", "model file cut to half its size", "error", "truncated or corrupt model file",
                "error naming the file", model=_write(out, "model_truncated.npz", data[: len(data) // 2]),
                culprit="model")


def _model_with(out, name: str, change) -> str:
    import io

    import numpy as np

    with np.load(io.BytesIO(_model_bytes(out)), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["metadata"]))
    change(meta)
    arrays["metadata"] = np.array(json.dumps(meta))
    with open(out / name, "wb") as fh:
        np.savez(fh, **arrays)
    return name


@_case
def model_wrong_version(out):
    path = out / _model_with(out, "model_wrong_version.npz", lambda m: m.update(format_version=99))
    return Case("model_wrong_version", "model file of format version 99 (incompatible)", "error",
                "format version 99 is not supported", "error naming the file", model=path.name, culprit="model")


@_case
def model_unknown_feature(out):
    def change(meta):
        meta["feature_names"][0] = "snr_db"
        meta["normaliser"]["feature_names"][0] = "snr_db"
    return Case("model_unknown_feature", "model file that needs a feature this lfgnss cannot compute", "error",
                "snr_db", "error naming the file and the feature (load_model and the CLI alike)",
                model=_model_with(out, "model_unknown_feature.npz", change), culprit="model")


@_case
def model_ok(out):
    _model_bytes(out)
    return Case("model_ok", "(control) a valid model file on the clean data", "ok", "", "solved with the model",
                model="model_ok.npz", culprit="model")


@_case
def model_not_a_model(out):
    return Case("model_not_a_model", "a RINEX file given as the model file", "error", "model file",
                "error naming the file", model="base.obs", culprit="model")


def build(out: str | Path, *, models: bool = True) -> dict[str, Case]:
    """Write the base files and every damaged input into ``out``; returns the cases by name.

    ``models=False`` skips the model-file cases (they need torch to export a network).
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    obs = base_obs()
    _write(out, "base.obs", obs.text())
    _write(out, "base3.rnx", to_v3(obs)[0])
    _write(out, "base.16n", _join(*base_nav("n")))
    _write(out, "base.16g", _join(*base_nav("g")))
    _write(out, "base_GT.txt", "\n".join(base_truth()) + "\n")
    cases = {}
    for fn in _BUILDERS:
        if not models and fn.__name__.startswith("model_"):
            continue
        case = fn(out)
        assert case.name == fn.__name__, fn.__name__
        cases[case.name] = case
    return cases


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    out = Path(argv[0]) if argv else Path(__file__).resolve().parent / "files"
    cases = build(out)
    total = sum(p.stat().st_size for p in out.iterdir())
    print(f"{len(cases)} cases, {len(list(out.iterdir()))} files, {total / 1e6:.2f} MB in {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
