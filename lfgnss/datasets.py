"""Benchmark datasets: files, ground truth, time alignment and splits, built into cached Sequences.

The three datasets of ``shared/BENCHMARK.md`` are registered by id; users add their own with a TOML
file (``register_toml``)::

    id = "my-drive"                   # letters, digits, '.', '_', '-' (it names cache files)
    obs = ["rover.obs"]               # paths relative to this file; several files of one receiver are
                                      # joined in time order (they must not overlap in time)
    nav = ["brdc.nav"]
    systems = ["G", "C"]              # optional: constellation letters of G, C, E, R, J (default: all)
    description = "my first drive"    # optional
    [truth]
    file = "truth.csv"
    format = "urbannav"               # urbannav | smartloc | static | ecef-csv | pos
    match_tolerance_s = 0.5           # optional: an epoch is labelled when a truth row lies this close [s]
                                      # (default 0.05 for smartloc, else 0.5, as python -m lfgnss.solve); its
                                      # truth is interpolated between the rows around it when they are at
                                      # most 2 s apart (TRUTH_INTERPOLATION_MAX_GAP_S), else the nearest row
    time_offset_s = 0                 # optional [s]: added to the truth's times as read, e.g. 18 for a truth
                                      # stamped in UTC (2017-2026), -28782 for one in Hong Kong time (UTC+8)
    # time_origin_gps_s = 1149246641.7  # smartloc truth or relative_s splits only (else refused: it would change
                                      # nothing): GPS seconds of a smartloc truth's t = 0, also the 0 of relative_s
                                      # splits; default the first observation epoch (as --truth-origin)
    [splits]                          # [start, stop) on the split axis (a command needs the splits it uses)
    axis = "tow"                      # tow | relative_s | epoch (tow: time of week of the first epoch's week,
                                      # 604800 + s in the next week)
    train = [46701, 46941]            # learning.train fits train and selects on val (data.train_split,
    val = [46941, 47001]              # data.val_split); lfgnss.benchmark scores test
    test = [47001, 47186]

A key not listed here (a typo) is refused, naming the file, the key and the keys known there.

Truth rows (numbers separated by commas or spaces; ``TRUTH_COLUMNS``):

- ``urbannav``: GPS week, TOW [s], latitude, longitude [deg], ellipsoidal height [m];
- ``smartloc``: ``point3``, t [s since ``time_origin_gps_s``], ECEF X, Y, Z [m] (libRSF; ``#`` lines are comments);
- ``static``: TOW [s], TOW [s], latitude, longitude [deg], ellipsoidal height [m]; the first row labels every epoch;
- ``ecef-csv``: GPS seconds since 1980-01-06, ECEF X, Y, Z [m];
- ``pos``: an RTKLIB ``.pos`` solution (``lfgnss.outputs.read_pos``: rnx2rtkp's or ``lfgnss.solve``'s).

Lines starting with ``%`` (RTKLIB's header) are comments in every format.
"""
from __future__ import annotations

import difflib
import hashlib
import json
import math
import numbers
import re
import tomllib
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .constants import SYSTEMS, unknown_systems
from .errors import InputError, UnknownNameError, did_you_mean, print_stdout
from .frames import NEAR_SURFACE_RADIUS_M, ecef_to_lla, lla_to_ecef
from .help_text import PlainHelp
from .paths import cache_file, file_digests, load_cached, names_something, shared_data_dir, store_cached
from .sequence import DEFAULT_FEATURES, Sequence, load_sequence, save_sequence
from .time import SECONDS_PER_WEEK, gps_s_to_week_tow, gpst_stamp, week_tow_to_gps_s

if TYPE_CHECKING:
    from .observations import Observations

# 9: no-fix epochs at the last earlier fix, cn0_std without blank C/N0; 8: truth interpolated between rows;
# 7: spp restarts from a wrong header position; 6: several obs files joined
_BUILD_VERSION = 9
SPLITS = ("train", "val", "test")
SPLIT_AXES = ("tow", "relative_s", "epoch")
#: Rows of a ``static`` truth file farther than this from its first row are not one point [m].
STATIC_SPREAD_M = 5.0
#: An epoch between two truth rows at most this far apart gets their linear interpolation, else the nearest row [s].
TRUTH_INTERPOLATION_MAX_GAP_S = 2.0


def _is_seconds(value: object, *, positive: bool = False) -> bool:
    """Whether ``value`` is a finite number (not a bool) of seconds, > 0 where ``positive``."""
    return (isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
            and (value > 0 or not positive))


def default_match_tolerance_s(truth_format: str) -> float:
    """Truth matching tolerance [s] when none is given: 0.05 for smartloc (5 Hz), else 0.5 (as the CLI)."""
    return 0.05 if truth_format == "smartloc" else 0.5


@dataclass(frozen=True)
class DatasetSpec:
    """Where a dataset's files are and how its truth and splits line up in time.

    Paths may be given as str. Several ``obs`` files are joined in time order. ``match_tolerance_s`` None:
    ``default_match_tolerance_s(truth_format)``; ``time_origin_gps_s`` None: the first observation epoch;
    ``time_offset_s`` [s] is added to every truth time as read (a truth stamped in UTC or local time, read as GPST).
    """

    id: str
    obs: tuple[Path, ...]
    nav: tuple[Path, ...]
    truth: Path
    truth_format: str
    splits: dict = field(default_factory=dict)   # name -> (start, stop) on split_axis, stop exclusive
    split_axis: str = "tow"                       # tow | relative_s | epoch
    systems: tuple[str, ...] | None = None
    match_tolerance_s: float | None = None        # [s]; None: 0.05 for smartloc, else 0.5
    time_origin_gps_s: float | None = None        # [GPS s] smartLoc t = 0 and relative_s 0; None: first epoch
    description: str = ""
    source: Path | None = None                    # the TOML file it was registered from (register_toml)
    time_offset_s: float = 0.0                    # [s] added to the truth's times (18 for UTC stamps in 2019)

    def __post_init__(self) -> None:
        def paths(value) -> tuple[Path, ...]:
            return (Path(value),) if isinstance(value, (str, Path)) else tuple(Path(p) for p in value)

        if id_problem(self.id):
            raise ValueError(f"DatasetSpec: {id_problem(self.id)}")
        object.__setattr__(self, "obs", paths(self.obs))
        object.__setattr__(self, "nav", paths(self.nav))
        object.__setattr__(self, "truth", Path(self.truth))
        if self.match_tolerance_s is None:
            object.__setattr__(self, "match_tolerance_s", default_match_tolerance_s(self.truth_format))
        offset, tolerance = self.time_offset_s, self.match_tolerance_s
        if not _is_seconds(offset):
            raise ValueError(f"DatasetSpec {self.id}: time_offset_s must be a finite number of seconds, got {offset!r}")
        if not _is_seconds(tolerance, positive=True):
            raise ValueError(f"DatasetSpec {self.id}: match_tolerance_s must be a number of seconds > 0 (how far an "
                             f"epoch may lie from a truth row), got {tolerance!r}")

    def files(self) -> list[Path]:
        """Every input file of the dataset."""
        return [*self.obs, *self.nav, self.truth]

    def missing(self) -> list[Path]:
        """Input files that do not exist (or are no file: a folder)."""
        return [p for p in self.files() if not p.is_file()]

    def missing_note(self) -> str:
        """``missing FILE`` (``FILE is a folder, not a file``) for the first missing input file ('' if none), with its
        key and TOML file if registered."""
        missing = self.missing()
        if not missing:
            return ""
        what = f"{missing[0]} is a folder, not a file" if missing[0].is_dir() else f"missing {missing[0]}"
        if self.source is None:
            return what + shared_data_hint(missing[0])
        key = "obs" if missing[0] in self.obs else "nav" if missing[0] in self.nav else "[truth] file"
        return f"{what} ({key} in {self.source})"


def shared_data_hint(path: Path) -> str:
    """Where the benchmark data are looked for, for a missing ``path`` inside that folder ('' for another path)."""
    if shared_data_dir() not in Path(path).parents:
        return ""
    return " (the benchmark datasets are read from $LFGNSS_SHARED_DATA, else ../shared/data beside the checkout)"


def _shared(folder: str, *names: str) -> tuple[Path, ...]:
    return tuple(shared_data_dir() / folder / n for n in names)


def _builtin() -> dict[str, DatasetSpec]:
    hk, bpp, st = "urbannav-hk-tst-20190428", "smartloc-berlin-potsdamer-platz-rinex", "hk-tst-static-20200603"
    return {
        "hk-tst-2019": DatasetSpec(
            "hk-tst-2019", _shared(hk, "COM3_190428_124409.obs"), _shared(hk, "hksc1180.19n", "hksc1180.19b"),
            _shared(hk, "groundTruth_TST.csv")[0], "urbannav",
            {"train": (46701, 46941), "val": (46941, 47001), "test": (47001, 47186)}, "tow", ("G", "C"), 0.5,
            description="UrbanNav HK TST 2019-04-28, u-blox GPS+BDS, 1 Hz deep urban drive"),
        "berlin-pp": DatasetSpec(
            "berlin-pp", _shared(bpp, "Berlin_Potsdamer_Platz.obs"), _shared(bpp, "brdc1580.16n", "brdc1580.16g"),
            _shared(bpp, "Berlin_Potsdamer_Platz_GT.txt")[0], "smartloc",
            {"train": (0.0, 150.0), "val": (150.0, 180.0), "test": (180.0, math.inf)}, "relative_s", ("G", "R"), 0.05,
            week_tow_to_gps_s(1900, 126641.7), "smartLoc Berlin Potsdamer Platz, u-blox GPS+GLONASS, ~5 Hz drive"),
        "hk-tst-static-2020": DatasetSpec(
            "hk-tst-static-2020", _shared(st, "2020_06_03_TST_03.obs"),
            tuple(shared_data_dir() / st / f"hksc155{h}.20{x}" for h in "cd" for x in "nglb"),
            _shared(st, "groundTruth_TST.csv")[0], "static",
            {"train": (0, 500), "val": (500, 600), "test": (600, math.inf)}, "epoch", ("G", "R", "E", "J", "C"), 0.5,
            description="HK TST static 2020-06-03, u-blox F9P G/R/E/J/C, one true point"),
    }


_REGISTRY: dict[str, DatasetSpec] = {}


def registered() -> dict[str, DatasetSpec]:
    """Every known dataset by id (built-in benchmark sets and user registrations)."""
    return {**_builtin(), **_REGISTRY}


def register(spec: DatasetSpec) -> DatasetSpec:
    """Make a dataset available by its id; InputError when another TOML file has registered another dataset (other
    files, truth, splits or settings) under that id already. The same file again (edited, say), or the same dataset
    from another file, replaces it."""
    other = _REGISTRY.get(spec.id)
    another_file = other is not None and spec.source and other.source and Path(other.source).resolve() != Path(
        spec.source).resolve()
    if another_file and _dataset_key(other) != _dataset_key(spec):
        raise InputError(spec.source, f"id {spec.id!r} is registered already, by {other.source}, for another dataset; "
                                      "give each dataset its own id")
    _REGISTRY[spec.id] = spec
    return spec


def _dataset_key(spec: DatasetSpec) -> DatasetSpec:
    """What tells datasets apart: files resolved (``..``, links), without the TOML it came from or its description."""
    files = lambda paths: tuple(Path(p).resolve() for p in paths)     # noqa: E731
    return replace(spec, obs=files(spec.obs), nav=files(spec.nav), truth=Path(spec.truth).resolve(), source=None,
                   description="")


#: The keys a dataset TOML may hold, at the top and in its tables (see the module docstring).
TOML_KEYS = ("id", "obs", "nav", "systems", "description", "truth", "splits")
TRUTH_KEYS = ("file", "format", "match_tolerance_s", "time_origin_gps_s", "time_offset_s")
#: Truth formats that give latitude and longitude in degrees written by hand or by other tools, where a file in
#: radians can be named as such (a .pos file is RTKLIB's, in degrees or ECEF).
GEODETIC_TRUTH_FORMATS = ("urbannav", "static")
#: Truth rows of one time whose positions lie farther apart than this [m] are refused (which one is the truth?).
TRUTH_REPEAT_M = 1.0
#: A dataset id of one's own: it names cache files, so no path separators (``my-drive``, ``hk_2021.a``).
DATASET_ID = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*")


def id_problem(dataset_id: object) -> str | None:
    """Why ``dataset_id`` cannot be a dataset id (``DATASET_ID``), or None."""
    if isinstance(dataset_id, str) and DATASET_ID.fullmatch(dataset_id):
        return None
    return (f"id {dataset_id!r} must be a name of letters, digits, '.', '_' or '-' starting with a letter or digit "
            f"(it names cache files)")
SPLIT_KEYS = ("axis", *SPLITS)
#: What ``get`` says about an unknown id: how a dataset of one's own becomes known, for every command.
REGISTER_HINT = ("register a dataset of your own first: --register FILE.toml, data.register = [\"FILE.toml\"] in "
                 "a training config, or lfgnss.datasets.register_toml in Python")


def _refuse_unknown_keys(path: Path, table: dict, known: tuple[str, ...], where: str = "") -> None:
    """InputError for the first key of ``table`` not in ``known``: the key, a close known one, and the known ones."""
    tables = () if where else ("truth", "splits")        # the top level's tables are shown as [truth], [splits]
    for key, value in table.items():
        if key in known:
            continue
        what = f"table [{key}]" if isinstance(value, dict) else f"key {key!r}"
        close = difflib.get_close_matches(key, known, n=1)
        guess = "" if not close else f" (did you mean [{close[0]}]?)" if close[0] in tables else \
            f" (did you mean {close[0]!r}?)"
        shown = ", ".join(f"[{k}]" if k in tables else k for k in known)
        raise InputError(path, f"unknown {what}{where}{guess}; known keys{where}: {shown}")


def _split_bounds(path: Path, name: str, value, axis: str) -> tuple[float, float]:
    """A ``[splits]`` entry as (start, stop), or an InputError saying what it must be."""
    ok = (isinstance(value, list) and len(value) == 2
          and all(isinstance(v, (int, float)) and not isinstance(v, bool) and not math.isnan(v) for v in value)
          and value[0] < value[1])
    if not ok:
        raise InputError(path, f"[splits] {name} must be [start, stop], two numbers (inf allowed) with start < stop "
                               f"(on the {axis} axis), got {value!r}")
    return value[0], value[1]


def find_dataset_toml(path: str | Path, look_in: tuple[str | Path, ...] = ()) -> Path:
    """A dataset TOML file: a relative ``path`` in the first folder of ``look_in`` that has it, else as given.

    InputError when it is in none of these places; for a relative ``path`` the message lists each place looked
    (the ``look_in`` folders, then the current one), absolute.
    """
    path = Path(path)
    places = list(dict.fromkeys([*(Path(folder) / path for folder in look_in), path]))
    for place in places:
        if names_something(place):
            return place
    looked = "" if path.is_absolute() else f"; looked for {', '.join(str(p.absolute()) for p in places)}"
    raise InputError(path, f"unreadable dataset config (No such file or directory{looked})")


def register_toml(path: str | Path, *, need_splits: tuple[str, ...] = ()) -> DatasetSpec:
    """Register a user dataset described by a TOML file (see the module docstring).

    Unknown keys, unknown constellation letters and malformed split bounds are refused (InputError naming the file
    and the key), as is the lack of a split named in ``need_splits`` (the splits a caller uses); a TOML without
    splits is valid where none is needed (``python -m lfgnss.summary``). A missing file's error lists where it was
    looked for (``find_dataset_toml``).
    """
    path = find_dataset_toml(path).absolute()          # its files stay the same ones if the current folder changes
    try:
        cfg = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as err:
        raise InputError(path, f"unreadable dataset config ({getattr(err, 'strerror', None) or err})") from None
    base = path.parent
    _refuse_unknown_keys(path, cfg, TOML_KEYS)
    for key in ("truth", "splits"):
        if not isinstance(cfg.get(key, {}), dict):
            raise InputError(path, f"[{key}] must be a table (e.g. [{key}] with file = ... / train = [a, b]), "
                                   f"got {cfg[key]!r}")
    _refuse_unknown_keys(path, cfg.get("truth", {}), TRUTH_KEYS, " in [truth]")
    _refuse_unknown_keys(path, cfg.get("splits", {}), SPLIT_KEYS, " in [splits]")
    for key in ("id", "obs", "nav", "truth"):
        if key not in cfg:
            raise InputError(path, f"dataset config lacks {'[truth] with file = ...' if key == 'truth' else key}")
    if "file" not in cfg["truth"]:
        raise InputError(path, "dataset config lacks file in [truth] (the ground-truth file)")
    if id_problem(cfg["id"]):
        raise InputError(path, f"{id_problem(cfg['id'])}, e.g. \"my-drive\"")
    for key in ("obs", "nav"):
        value = cfg[key]
        if not (isinstance(value, str) or isinstance(value, list) and value and all(isinstance(v, str) for v in value)):
            raise InputError(path, f"{key} must be a file name or a list of file names, got {value!r}")
        if isinstance(value, str):
            cfg[key] = [value]
    if not isinstance(cfg["truth"]["file"], str):
        raise InputError(path, f"file in [truth] must be a file name, got {cfg['truth']['file']!r}")
    axis = cfg.get("splits", {}).get("axis", "tow")
    axis = axis.lower() if isinstance(axis, str) else axis          # any case, as the truth format
    if axis not in SPLIT_AXES:
        raise InputError(path, f"unknown split axis {axis!r} in [splits]; use one of {', '.join(SPLIT_AXES)}")
    splits = {k: _split_bounds(path, k, v, axis) for k, v in cfg.get("splits", {}).items() if k in SPLITS}
    names = [k for k in SPLITS if k in splits]
    for i, a in enumerate(names):                 # a model must never be trained or selected on test epochs
        for b in names[i + 1:]:
            if splits[a][0] < splits[b][1] and splits[b][0] < splits[a][1]:
                raise InputError(path, f"[splits] {a} {list(splits[a])} and {b} {list(splits[b])} overlap (on the "
                                       f"{axis} axis, [start, stop)); splits must not share epochs")
    if str(cfg.get("id")) in _builtin():
        raise InputError(path, f"id {cfg['id']!r} is a benchmark dataset of shared/BENCHMARK.md; give yours another id")
    lacking = [k for k in need_splits if k not in splits]
    if lacking:
        raise InputError(path, f"[splits] has no {' or '.join(lacking)}, which this command uses; give "
                               f"{lacking[0]} = [start, stop] on the {axis} axis "
                               f"(it has {', '.join(splits) or 'none'})")
    systems = cfg.get("systems")
    if systems is not None:
        if isinstance(systems, str):
            systems = [c for c in systems if c not in " ,"]     # "GR", "G R", "G,R": the letters, as --systems
        if isinstance(systems, list) and all(isinstance(s, str) for s in systems):
            systems = [s.strip().upper() for s in systems]     # any case, as --systems
        if not isinstance(systems, list) or not systems or not all(isinstance(s, str) for s in systems):
            raise InputError(path, f"systems must be a list of constellation letters of {''.join(SYSTEMS)} "
                                   f"(e.g. [\"G\", \"C\"]), got {cfg['systems']!r}")
        unknown = unknown_systems(systems)
        if unknown:
            raise InputError(path, f"unknown constellation letter(s) {unknown} in systems; use {''.join(SYSTEMS)}")
    for key in ("obs", "nav"):
        if isinstance(cfg.get(key), str):
            cfg[key] = [cfg[key]]                      # one file may be given without a list
        if not cfg[key]:
            raise InputError(path, f"dataset config lists no {key} file")
    offset = cfg["truth"].get("time_offset_s", 0.0)
    if not _is_seconds(offset):
        raise InputError(path, f"time_offset_s in [truth] must be a number of seconds added to the truth's times "
                               f"(18 for a truth stamped in UTC in 2017-2026), got {offset!r}")
    tolerance = cfg["truth"].get("match_tolerance_s")
    if tolerance is not None and not _is_seconds(tolerance, positive=True):
        raise InputError(path, f"match_tolerance_s in [truth] must be a number of seconds > 0 (how far an epoch may "
                               f"lie from a truth row), got {tolerance!r}")
    truth_format = str(cfg["truth"].get("format", "urbannav")).lower()
    if truth_format not in TRUTH_READERS:
        raise InputError(path, f"unknown truth format {truth_format!r} in [truth]; use one of "
                               f"{', '.join(TRUTH_READERS)}{did_you_mean(truth_format, list(TRUTH_READERS))}")
    if cfg["truth"].get("time_offset_s") and truth_format == "static":
        raise InputError(path, "time_offset_s in [truth] would change nothing for a static truth, whose one point "
                               "labels every epoch; remove it")
    if "time_origin_gps_s" in cfg["truth"] and truth_format != "smartloc" and axis != "relative_s":
        raise InputError(path, f"time_origin_gps_s in [truth] is the t = 0 of a smartloc truth and of relative_s "
                               f"splits, and this dataset has neither (format = {truth_format!r}, axis = {axis!r}): "
                               f"it would change nothing; remove it (a {truth_format} truth is stamped in GPS time: "
                               "times off by a constant are to be shifted in the file)")

    def file(name: str) -> Path:
        return base / Path(name).expanduser()       # relative to the TOML's folder; ~ is the home folder

    try:
        truth = cfg["truth"]
        origin = truth.get("time_origin_gps_s")
        spec = DatasetSpec(
            id=str(cfg["id"]), obs=tuple(file(p) for p in cfg["obs"]), nav=tuple(file(p) for p in cfg["nav"]),
            truth=file(truth["file"]), truth_format=truth_format, splits=splits,
            split_axis=str(axis), systems=None if systems is None else tuple(systems),
            match_tolerance_s=None if tolerance is None else float(tolerance),
            time_origin_gps_s=None if origin is None else float(origin), time_offset_s=float(offset),
            description=str(cfg.get("description", "")),
            source=path)
    except (KeyError, TypeError, ValueError) as err:
        raise InputError(path, f"dataset config lacks or misuses {err}") from None
    return register(spec)


def get(dataset_id: str, *, hint: str | None = None) -> DatasetSpec:
    """The spec of a dataset id, or a KeyError listing the known ones and ``hint`` (default ``REGISTER_HINT``)."""
    specs = registered()
    if dataset_id not in specs:
        more = REGISTER_HINT if hint is None else hint
        raise UnknownNameError(f"unknown dataset {dataset_id!r}{did_you_mean(dataset_id, sorted(specs))}; known: "
                               f"{', '.join(sorted(specs))}" + (f" ({more})" if more else ""))
    return specs[dataset_id]


# -- ground truth -------------------------------------------------------------------------------------------

#: A ground truth point is near the Earth's surface: ECEF radius [m] within these bounds (ocean floor to airliner
#: height and more), ellipsoidal height [m] within TRUTH_HEIGHT_M.
TRUTH_RADIUS_M = NEAR_SURFACE_RADIUS_M
TRUTH_HEIGHT_M = (-1.0e4, 1.0e5)
GPS_WEEK_MAX = 9999             # full GPS weeks since 1980-01-06 (week 9999 is in 2171)


def _lla_problem(values: list[float]) -> str | None:
    """Why a row of (time, time, latitude [deg], longitude [deg], height [m]) is no position on Earth, or None."""
    lat, lon, h = values[2:5]
    if not -90.0 <= lat <= 90.0:
        return f"latitude {lat:g} deg outside [-90, 90]"
    if not -180.0 <= lon <= 360.0:
        return f"longitude {lon:g} deg outside [-180, 360]"
    if not TRUTH_HEIGHT_M[0] <= h <= TRUTH_HEIGHT_M[1]:
        return f"height {h:g} m outside [{TRUTH_HEIGHT_M[0]:g}, {TRUTH_HEIGHT_M[1]:g}]"
    return None


def _week_tow_problem(values: list[float]) -> str | None:
    """Why a row of (GPS week, TOW [s], latitude [deg], longitude [deg], height [m]) is no position in time, or None.

    A static file's first column (a time of week, 0-604800 s) read as the week fails here, so the file is not taken
    for urbannav truth whose every time is thousands of weeks off.
    """
    week, tow = values[:2]
    if not (0 <= week <= GPS_WEEK_MAX and week == int(week)):
        return f"GPS week {week:g} is not a whole number in [0, {GPS_WEEK_MAX}]"
    if not 0.0 <= tow <= SECONDS_PER_WEEK:
        return f"time of week {tow:g} s outside [0, {SECONDS_PER_WEEK:g}]"
    return _lla_problem(values)


def _ecef_problem(values: list[float]) -> str | None:
    """Why a row of (time, X, Y, Z [m]) is no position near the Earth's surface, or None."""
    r = math.hypot(*values[1:4])                   # no overflow to inf at 1e308
    if not TRUTH_RADIUS_M[0] <= r <= TRUTH_RADIUS_M[1]:
        low, high = TRUTH_RADIUS_M
        return f"ECEF position {r:.6g} m from the Earth's centre, outside [{low:g}, {high:g}]"
    return None


def _numeric_rows(path: Path, n_cols: int, record_word: str | None = None,
                  problem=None) -> tuple[np.ndarray, list[str]]:
    """Rows of at least n_cols numbers; bad lines are reported as 'PATH:LINE: reason' and skipped.

    With ``record_word`` only lines starting with that word are rows; others are reported, '#' comments aside.
    Lines starting with '%' (RTKLIB's .pos header) are comments in every format; a UTF-8 byte order mark is read
    past. ``problem(values) -> reason or None`` rejects rows of readable but impossible values.
    """
    rows, skipped = [], []          # skipped: (line number, reason)
    try:
        lines = path.read_text(encoding="utf-8-sig", errors="replace").splitlines()
    except OSError as err:
        raise InputError(path, f"cannot read truth file ({err.strerror})") from None
    for i, line in enumerate(lines, 1):
        if not line.strip() or line.lstrip().startswith("%"):
            continue
        parts = line.replace(",", " ").split()
        if record_word is not None:
            if parts[0].startswith("#"):
                continue
            if parts[0] != record_word:
                skipped.append((i, f"not a {record_word} record"))
                continue
            parts = parts[1:]
        try:
            values = [float(p) for p in parts[:n_cols]]
            if len(values) < n_cols or not np.all(np.isfinite(values)):
                raise ValueError
        except ValueError:
            skipped.append((i, "unreadable truth line" + _unreadable_why(line, first=not rows and not skipped)))
            continue
        why = problem(values) if problem is not None else None
        if why is not None:
            skipped.append((i, why))
            continue
        rows.append(values)
    if not rows:
        if skipped:             # say why at the first line (words above no row are no header)
            why = skipped[0][1].removesuffix(" (a header?)")
            raise InputError(path, f"no readable ground-truth line; the first: {why}", line=skipped[0][0])
        raise InputError(path, "no readable ground-truth line")
    return np.array(rows), [f"{path}:{i}: {why}, skipped" for i, why in skipped]


def _unreadable_why(line: str, first: bool) -> str:
    """Words after "unreadable truth line" when ``line`` shows why: a calendar date, semicolons, words on the
    first line (a header), else ''."""
    if re.match(r"\s*\d{4}[/-]\d{1,2}[/-]\d{1,2}", line):
        return (" (a calendar date: truth times are numbers of GPS time, see the format's columns; an RTKLIB .pos "
                "file reads as format pos)")
    if ";" in line:
        return " (semicolon-separated: separate numbers by commas or spaces, with decimal points)"
    return " (a header?)" if first and any(c.isalpha() for c in line) else ""


#: Each truth format's rows, as _numeric_rows' (numbers per row, record word, plausibility check).
_ROW_LAYOUTS = {"urbannav": (5, None, _week_tow_problem), "smartloc": (4, "point3", _ecef_problem),
                "static": (5, None, _lla_problem), "ecef-csv": (4, None, _ecef_problem)}

#: The columns of each truth format's rows (comma- or space-separated; '#' lines are comments in smartloc files).
TRUTH_COLUMNS = {
    "urbannav": "GPS week, TOW [s], latitude, longitude [deg], ellipsoidal height [m]",
    "smartloc": "the word point3, t [s since the truth origin: --truth-origin or time_origin_gps_s, default the "
                "first epoch], ECEF X, Y, Z [m]",
    "static": "TOW [s], TOW [s], latitude, longitude [deg], ellipsoidal height [m]; the first row labels every epoch",
    "ecef-csv": "GPS seconds since 1980-01-06, ECEF X, Y, Z [m]",
    "pos": "an RTKLIB .pos solution (rnx2rtkp's or lfgnss.solve's): GPST or UTC, week/TOW or calendar time, "
           "latitude/longitude/height or ECEF",
}


def _readable_as(path: Path, truth_format: str) -> str | None:
    """Another truth format in which ``path`` has readable rows, or None (a hint for a wrong format setting).

    ``static`` is named only for rows of one point: a drive's urbannav file with a bad week column (TOW in ms, a
    week of -1) reads as static too, and static truth would label every epoch with its first row.
    """
    for other, layout in _ROW_LAYOUTS.items():
        if other != truth_format and _ROW_LAYOUTS.get(truth_format) != layout:      # "pos" has no row layout
            try:
                rows, _ = _numeric_rows(path, *layout)
            except InputError:
                continue
            if other == "static" and _static_points(rows)[1] > STATIC_SPREAD_M:
                continue
            return other
    return None


def read_urbannav(path: Path, spec: DatasetSpec) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """UrbanNav CSV: GPS week, TOW [s], latitude, longitude [deg], height [m]."""
    rows, bad = _numeric_rows(path, *_ROW_LAYOUTS["urbannav"])
    return week_tow_to_gps_s(rows[:, 0], rows[:, 1]), lla_to_ecef(np.radians(rows[:, 2]), np.radians(rows[:, 3]), rows[:, 4]), bad


def read_smartloc(path: Path, spec: DatasetSpec) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """libRSF ``point3`` rows: t [s since spec.time_origin_gps_s, which align_truth fills in], ECEF X Y Z [m]."""
    if spec.time_origin_gps_s is None:
        raise ValueError(f"dataset {spec.id}: smartloc truth needs time_origin_gps_s (align_truth sets it)")
    rows, bad = _numeric_rows(path, *_ROW_LAYOUTS["smartloc"])
    return spec.time_origin_gps_s + rows[:, 0], rows[:, 1:4], bad


def _static_points(rows: np.ndarray) -> tuple[np.ndarray, float]:
    """ECEF points (R, 3) [m] of static truth rows (TOW, TOW, lat, lon [deg], h [m]) and how far [m] they lie from the
    first."""
    xyz = lla_to_ecef(np.radians(rows[:, 2]), np.radians(rows[:, 3]), rows[:, 4])
    return xyz, float(np.max(np.linalg.norm(xyz - xyz[0], axis=1)))


def read_static(path: Path, spec: DatasetSpec) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """One static point: rows of TOW, TOW, latitude, longitude [deg], height [m]; labels every epoch.

    The first row is the point; rows farther than ``STATIC_SPREAD_M`` from it give a warning (not one point).
    """
    rows, bad = _numeric_rows(path, *_ROW_LAYOUTS["static"])
    xyz, spread_m = _static_points(rows)
    if spread_m > STATIC_SPREAD_M:
        warnings.warn(f"{path}: static truth rows lie up to {spread_m:.0f} m from the first, not one point; that row "
                      f"labels every epoch (for a moving receiver use format urbannav or ecef-csv)", stacklevel=2)
    return np.array([-np.inf]), xyz[:1], bad


def static_time_note(path: str | Path, time_gps_s: np.ndarray, tolerance_s: float = 0.5) -> str | None:
    """Why a static truth file may be of another session: its times of week [s] miss the epochs' [GPS s], or None.

    Only a file whose first column holds times of week (in [0, 604800) s, not all 0) is checked; a week rollover
    within the epochs counts as overlapping. Its point labels every epoch all the same (``read_static``).
    """
    tow = _numeric_rows(Path(path), *_ROW_LAYOUTS["static"])[0][:, 0]
    epochs_tow = gps_s_to_week_tow(np.asarray(time_gps_s, dtype=float))[1]
    if not epochs_tow.size or not (np.all((tow >= 0) & (tow < SECONDS_PER_WEEK)) and tow.max() > 0):
        return None
    if tow.min() <= epochs_tow.max() + tolerance_s and tow.max() >= epochs_tow.min() - tolerance_s:
        return None
    return (f"{path}: its times of week ({tow.min():.0f} to {tow.max():.0f} s) do not overlap the observations' "
            f"({epochs_tow.min():.0f} to {epochs_tow.max():.0f} s): a static truth of another session or place? "
            f"Its point labels every epoch all the same")


def read_ecef_csv(path: Path, spec: DatasetSpec) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """CSV of GPS seconds since 1980-01-06, ECEF X, Y, Z [m]."""
    rows, bad = _numeric_rows(path, *_ROW_LAYOUTS["ecef-csv"])
    return rows[:, 0], rows[:, 1:4], bad


def read_pos_truth(path: Path, spec: DatasetSpec) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """An RTKLIB ``.pos`` file (rnx2rtkp's or ``python -m lfgnss.solve``'s): every solution line's time [GPS s] and
    ECEF position [m] (``lfgnss.outputs.read_pos``: week/TOW or calendar time, GPST or UTC, lat/lon/height or ECEF;
    lines of Q = 0, RTKLIB's "no solution", or off the Earth are skipped with a note; any other Q is kept)."""
    from .outputs import read_pos

    try:
        sol = read_pos(path)
    except OSError as err:
        raise InputError(path, f"cannot read truth file ({err.strerror})") from None
    except ValueError as err:
        where = re.match(r"read_pos .*?:(\d+): (.*)", str(err))
        raise InputError(path, where.group(2) if where else f"not readable as an RTKLIB .pos solution ({err})",
                         line=int(where.group(1)) if where else None) from None
    if not sol.time_gps_s.size:
        raise InputError(path, "no readable ground-truth line (no solution line in this .pos file)")
    radius = np.linalg.norm(sol.pos_ecef_m, axis=1)
    low, high = TRUTH_RADIUS_M
    # Q = 0 is RTKLIB's "no solution" (its position, often 0, 0, 0 in either frame, is none); off the Earth: junk
    off = (np.asarray(sol.info["q"]) == 0) | ~((radius >= low) & (radius <= high))
    if off.all():
        raise InputError(path, "no readable ground-truth line: every solution line has Q = 0 (no solution) or lies "
                               f"off the Earth (the first {radius[0]:.6g} m from its centre)")
    notes = [f"{path}: {int(off.sum())} solution line(s) with Q = 0 (no solution) or off the Earth (the first at GPS "
             f"{sol.time_gps_s[off][0]:.1f} s), skipped"] if off.any() else []
    return sol.time_gps_s[~off], sol.pos_ecef_m[~off], notes


TRUTH_READERS = {"urbannav": read_urbannav, "smartloc": read_smartloc, "static": read_static, "ecef-csv": read_ecef_csv,
                 "pos": read_pos_truth}


#: A truth lying a median farther than this from the coarse least-squares fixes is likely of another drive or place
#: [m]: the median least-squares error is 40 to 90 m on the three benchmark datasets (200 m at worst on an epoch).
TRUTH_MISMATCH_M = 1000.0
#: Unix time of the GPS epoch 1980-01-06 [s] (leap seconds aside).
UNIX_TO_GPS_S = 315964800.0
#: Time shifts of a moving truth tried against the coarse fixes [s]: a wrong smartloc origin, UTC stamps (17-18 s).
TRUTH_SHIFTS_S = np.arange(-60.0, 60.0 + 1e-9, 0.5)
#: A shift is taken for the truth's when it brings the truth's median horizontal distance from the coarse fixes to at
#: most this fraction of the unshifted one, and at least this much [m] closer. On the benchmark drives the unshifted
#: truth lies a median 12 m (hk-tst-2019) and 29 m (berlin-pp) from the fixes horizontally and no shift comes closer
#: than 0.93 of that; shifted by 5 s their truths lie 35 and 33-46 m off, by 10 s 47-53 and 52-70 m, by 18-20 s 62-120 m
#: (session 49): on hk a shift of 5 s is found; on the Berlin drive, whose fixes lag its truth by about 1.5 s, one of
#: 5 s early or 9 s late; a second or two never.
TRUTH_SHIFT_RATIO = 0.6
TRUTH_SHIFT_GAIN_M = 15.0
#: Shorter stretches of epochs with truth and a fix are not checked [s], nor ones holding less than half this of
#: epochs: over 20-30 s the fixes' slowly varying error fits a shifted truth better on 3-8 % of the benchmark drives'
#: windows with right truth (none from 45 s), and two 5-10 s pieces far apart on 1-4 % of such pairs.
TRUTH_SHIFT_MIN_SPAN_S = 120.0
#: The scan reads at most this many epochs, evenly spread (the truth file is read again all the same).
TRUTH_SHIFT_EPOCHS = 3000
#: A best shift this close to -(GPST - UTC) [s], whose UTC reading fits too and lies at most this factor from the
#: best shift's median, is named as UTC stamps (the bundled drive stamped in UTC: 1.19; hk-tst-2019's truth 16 or
#: 20 s early read as UTC: 1.6-1.7).
TRUTH_SHIFT_UTC_S = 2.5
TRUTH_SHIFT_UTC_RATIO = 1.25


def truth_fit_notes(spec: DatasetSpec, time_gps_s: np.ndarray, truth_ecef_m: np.ndarray,
                    fix_ecef_m: np.ndarray) -> list[str]:
    """Why a truth file may be wrong for these epochs, from the coarse fixes (T, 3) [m]: one line each, or none.

    ``truth_ecef_m`` (T, 3) [m] is :func:`align_truth`'s at ``time_gps_s`` [GPS s]. A truth lying a median over
    ``TRUTH_MISMATCH_M`` from the fixes is of another drive or place; a static truth whose times of week miss the
    epochs of another session (``static_time_note``); a moving truth that fits the fixes far better shifted in time
    has its times off: stamped in UTC (GPST - UTC) or a wrong smartloc origin (``truth_shift_note``).
    """
    truth, fix = np.asarray(truth_ecef_m, float), np.asarray(fix_ecef_m, float)
    both = np.isfinite(truth).all(axis=1) & np.isfinite(fix).all(axis=1)
    notes = [static_time_note(spec.truth, time_gps_s)] if spec.truth_format == "static" else []
    if both.any():
        median_m, _ = median_truth_gap_m(truth, fix)
        if median_m > TRUTH_MISMATCH_M:
            distance = f"{median_m / 1000:.0f} km" if median_m >= 10_000 else f"{median_m / 1000:.1f} km"
            origin = f", or a wrong {_origin_words(spec)}" if spec.truth_format == "smartloc" else ""
            if (spec.truth_format in GEODETIC_TRUTH_FORMATS and _within_radian_bounds(truth[both])
                    and not _within_radian_bounds(fix[both])):
                origin += " (its latitudes and longitudes, all within 1.6 and 6.3, look like radians, not degrees)"
            notes.append(f"{spec.truth}: the truth lies a median {distance} from the receiver's least-squares fixes "
                         f"(on {int(both.sum())} epochs): a truth file of another drive or place{origin}? It is scored "
                         "all the same")
        elif spec.truth_format != "static":
            notes.append(truth_shift_note(spec, time_gps_s, truth, fix))
    return [n for n in notes if n]


def median_truth_gap_m(truth_ecef_m: np.ndarray, fix_ecef_m: np.ndarray) -> tuple[float, int]:
    """Median distance [m] between truth and fixes (T, 3) [m] over the epochs where both are finite, and how many
    those are (NaN, 0 if none)."""
    both = np.isfinite(truth_ecef_m).all(axis=1) & np.isfinite(fix_ecef_m).all(axis=1)
    if not both.any():
        return float("nan"), 0
    return float(np.median(np.linalg.norm(truth_ecef_m[both] - fix_ecef_m[both], axis=1))), int(both.sum())


def _within_radian_bounds(ecef_m: np.ndarray) -> bool:
    """Whether every latitude and longitude of the positions (N, 3) [m], in degrees, lies within what radians can be
    (|lat| <= pi/2, |lon| <= 2 pi): a truth written in radians and read as degrees does."""
    lla = ecef_to_lla(ecef_m).reshape(-1, 3)
    lat_deg, lon_deg = np.degrees(lla[:, 0]), np.degrees(lla[:, 1])
    return bool((np.abs(lat_deg) <= np.pi / 2).all() and (np.abs(lon_deg) <= 2 * np.pi).all())


def unmatched_time_words(spec: DatasetSpec, time_gps_s: np.ndarray) -> str:
    """Where a truth that labels no epoch has its times, against the epochs' [GPS s], when that tells what is wrong:
    ``; its times (a to b s) look like times of week ...``, with the ``time_offset_s`` that fixes it where one does,
    or ''. The file's own times are judged (any ``time_offset_s`` given is replaced by the one named)."""
    if spec.truth_format not in ("ecef-csv", "urbannav") or not np.size(time_gps_s):
        return ""
    try:
        t_truth = TRUTH_READERS[spec.truth_format](spec.truth, spec)[0]
    except InputError:
        return ""
    from .time import leap_seconds

    times = np.asarray(time_gps_s, float)
    leap = float(np.median(leap_seconds(times)))
    first, last = float(np.min(t_truth)), float(np.max(t_truth))
    epochs = f"the epochs' are GPS {float(np.min(times)):.1f} to {float(np.max(times)):.1f} s"
    span = f"its times ({first:.10g} to {last:.10g} s)"
    if spec.truth_format == "ecef-csv" and 0 <= first and last < SECONDS_PER_WEEK:
        week = float(np.floor(np.min(times) / SECONDS_PER_WEEK) * SECONDS_PER_WEEK)
        return (f"; {span} look like times of week: ecef-csv times are GPS seconds since 1980-01-06 (week * 604800 + "
                f"time of week): {offset_words(spec, week)}; and {epochs}")
    if spec.truth_format == "ecef-csv" and np.min(times) - 86400 <= first / 1000 <= np.max(times) + 86400:
        return f"; {span} look like milliseconds: ecef-csv times are seconds, and {epochs}"
    if spec.truth_format == "ecef-csv" and abs(first - UNIX_TO_GPS_S - np.min(times)) <= 86400:
        return (f"; {span} look like Unix times (seconds since 1970, UTC): ecef-csv times are GPS seconds since "
                f"1980-01-06, {UNIX_TO_GPS_S:.0f} s fewer (and GPST - UTC more): "
                f"{offset_words(spec, leap - UNIX_TO_GPS_S)}; and {epochs}")
    for weeks in (1024, 2048):          # a receiver's 10-bit week number that rolled over (1999, 2019)
        shift = weeks * SECONDS_PER_WEEK
        if first + shift <= np.max(times) and last + shift >= np.min(times):
            return (f"; {span} lie exactly {weeks} weeks before the epochs, as a 10-bit GPS week number that rolled "
                    f"over reads them: {offset_words(spec, shift)}; and {epochs}")
    zone_h = _zone_offset_h(t_truth, times - leap, spec.match_tolerance_s)
    if zone_h is not None:
        return (f"; {span} would fit the epochs as local time, about UTC{zone_h:+g} h: {spec.truth_format} times are "
                f"GPST, so {'subtract' if zone_h > 0 else 'add'} {abs(zone_h):g} h and add GPST - UTC ({leap:g} s "
                f"here): {offset_words(spec, leap - zone_h * 3600.0)}; and {epochs}")
    return f"; {span.replace('its times', 'its GPS times')} miss them: {epochs}"


def _zone_offset_h(t_truth: np.ndarray, utc: np.ndarray, tolerance_s: float) -> float | None:
    """The time zone [h from UTC, quarter hours, 0.5 to 14 h either way] in which truth times [s] stamped in local time
    overlap the epochs (``utc``, their UTC times [s]) longest, whole hours first among equals (a short truth lies
    within a long drive at many zones), then the nearest to the one the spans' middles give; None where no zone makes
    them overlap."""
    if not t_truth.size or not utc.size:
        return None
    middles_h = (np.ptp(t_truth) / 2 + t_truth.min() - np.ptp(utc) / 2 - utc.min()) / 3600.0
    zones = [z for z in np.arange(-14.0, 14.25, 0.25) if abs(z) >= 0.5]

    def overlap_s(zone_h: float) -> float:
        local = utc + zone_h * 3600.0
        return min(t_truth.max(), local.max() + tolerance_s) - max(t_truth.min(), local.min() - tolerance_s)

    best = max(zones, key=lambda z: (round(overlap_s(z), 3), float(z).is_integer(), -abs(z - middles_h)))
    return float(best) if overlap_s(best) >= 0 else None


def _origin_words(spec: DatasetSpec) -> str:
    """Where a smartloc truth's t = 0 is given: ``--truth-origin``, or the key in the dataset's TOML file."""
    return f"time_origin_gps_s in [truth] of {spec.source}" if spec.source else "--truth-origin"


def truth_shift_note(spec: DatasetSpec, time_gps_s: np.ndarray, truth_ecef_m: np.ndarray,
                     fix_ecef_m: np.ndarray) -> str | None:
    """A note when a moving truth fits the coarse fixes (T, 3) [m] far better read some seconds off, or None.

    ``spec.time_origin_gps_s`` must be the origin the truth was read with (None: ``time_gps_s[0]``). Over at least
    ``TRUTH_SHIFT_MIN_SPAN_S`` of epochs with both (at most ``TRUTH_SHIFT_EPOCHS`` of them, evenly spread), each
    shift of ``TRUTH_SHIFTS_S`` reads the truth at the epochs' times plus the shift; the one with the smallest median
    horizontal distance from the fixes, on at least 80 % of those epochs, is named when it passes
    ``TRUTH_SHIFT_RATIO`` and ``TRUTH_SHIFT_GAIN_M``: as UTC stamps (urbannav, ecef-csv) when GPST - UTC lies within
    ``TRUTH_SHIFT_UTC_S`` of it and passes too, else as that shift, to a second or two (the fixes' own lag).
    """
    from .frames import ecef_to_enu
    from .time import leap_seconds

    time_gps_s = np.asarray(time_gps_s, dtype=float)
    origin = time_gps_s[0] if spec.time_origin_gps_s is None else spec.time_origin_gps_s    # as align_truth read it
    both = np.flatnonzero(np.isfinite(truth_ecef_m).all(axis=1) & np.isfinite(fix_ecef_m).all(axis=1))
    step = float(np.median(np.diff(time_gps_s))) if time_gps_s.size > 1 else 0.0
    if (both.size < 10 or np.ptp(time_gps_s[both]) + step < TRUTH_SHIFT_MIN_SPAN_S
            or both.size * step < TRUTH_SHIFT_MIN_SPAN_S / 2):
        return None         # a short stretch: the fixes' slowly varying error can fit a shift better by chance
    both = both[np.unique(np.linspace(0, both.size - 1, min(both.size, TRUTH_SHIFT_EPOCHS)).astype(int))]
    time_gps_s, fix_ecef_m = time_gps_s[both], np.asarray(fix_ecef_m, float)[both]
    t_truth, xyz, _ = _sorted_truth_rows(spec, origin)
    ref = np.median(np.asarray(truth_ecef_m, float)[both], axis=0)
    fix_en = ecef_to_enu(fix_ecef_m, ref)[:, :2]

    def median_m(shift_s: float) -> tuple[float, int]:
        at = _truth_at(time_gps_s + shift_s, t_truth, xyz, spec.match_tolerance_s)
        ok = np.isfinite(at).all(axis=1)
        d = np.linalg.norm(ecef_to_enu(at[ok], ref)[:, :2] - fix_en[ok], axis=1)
        return (float(np.median(d)) if ok.any() else math.inf), int(ok.sum())

    def fits(shifted_m: float) -> bool:
        return shifted_m <= TRUTH_SHIFT_RATIO * unshifted and unshifted - shifted_m >= TRUTH_SHIFT_GAIN_M

    def words(shifted_m: float, shift_s: float, about: str = "") -> str:
        change = f"{about}{abs(shift_s):g} s {'added to' if shift_s < 0 else 'taken from'} its times"
        return (f"{spec.truth}: the truth lies a median {shifted_m:.0f} m horizontally from the receiver's "
                f"least-squares fixes with {change}, against {unshifted:.0f} m as stamped (on {n} epochs checked)")

    unshifted, n = median_m(0.0)
    best_m, shift = min((m, s) for s in TRUTH_SHIFTS_S for m, k in [median_m(float(s))] if k >= 0.8 * n)
    if not fits(best_m):
        return None
    leap = float(np.median(leap_seconds(time_gps_s)))
    if spec.truth_format in ("urbannav", "ecef-csv") and abs(shift + leap) <= TRUTH_SHIFT_UTC_S:
        as_utc = median_m(-leap)        # UTC stamps: GPST - UTC too few seconds
        if as_utc[1] >= 0.8 * n and fits(as_utc[0]) and as_utc[0] <= TRUTH_SHIFT_UTC_RATIO * best_m:
            return (f"{words(as_utc[0], -leap)}: are its times UTC? {spec.truth_format} times are GPST (GPST - UTC = "
                    f"{leap:g} s here): {offset_words(spec, spec.time_offset_s + leap)}; it is scored as stamped all "
                    "the same")
    if spec.truth_format == "smartloc":
        return (f"{words(best_m, shift, 'about ')}: a wrong {_origin_words(spec)}? About GPS {origin - shift:.1f} s "
                "fits; it is scored as stamped all the same")
    fix = offset_words(spec, spec.time_offset_s - shift, "about ")
    return f"{words(best_m, shift, 'about ')}: are its times off? ({fix}); it is scored as stamped all the same"


def offset_words(spec: DatasetSpec, total_s: float, about: str = "") -> str:
    """How to have ``total_s`` [s] added to a truth's times as read: the ``time_offset_s`` key of the dataset's TOML
    file, else ``lfgnss.solve``'s option (to 0.1 s, never in exponent form)."""
    value = f"{round(total_s, 1):.1f}".removesuffix(".0")
    if spec.source:
        return f"give {about}time_offset_s = {value} in [truth] of {spec.source}"
    return f"give {about}--truth-offset {value}"


def read_truth(path: str | Path, time_gps_s: np.ndarray, truth_format: str = "urbannav", *,
               time_origin_gps_s: float | None = None, match_tolerance_s: float | None = None,
               time_offset_s: float = 0.0) -> np.ndarray:
    """(T, 3) ECEF ground truth [m] at epoch times [GPS s] from a truth file; NaN where none lies within the tolerance.

    ``truth_format``: one of ``TRUTH_READERS``, in any case; a smartloc file counts its t from
    ``time_origin_gps_s`` (default: the first epoch); ``time_offset_s`` [s] is added to every truth time (18 for UTC
    stamps in 2017-2026). Skipped lines are warned about (the first five, then a count).
    """
    truth_format = truth_format.lower() if isinstance(truth_format, str) else truth_format    # as --truth-format
    if truth_format not in TRUTH_READERS:
        raise InputError(path, f"unknown truth format {truth_format!r}; use one of {', '.join(TRUTH_READERS)}")
    spec = DatasetSpec("truth", (), (), path, truth_format, match_tolerance_s=match_tolerance_s,
                       time_origin_gps_s=time_origin_gps_s, time_offset_s=time_offset_s)
    truth, notes = align_truth(time_gps_s, spec)
    for note in truth_note_summary(path, notes):
        warnings.warn(note, stacklevel=2)
    return truth


def align_truth(time_gps_s: np.ndarray, spec: DatasetSpec) -> tuple[np.ndarray, list[str]]:
    """(T, 3) ground truth for epoch times [s] (NaN where no row within the tolerance) and reader notes.

    The truth is interpolated between the rows around each epoch (:func:`interpolate_truth`).
    A spec without ``time_origin_gps_s`` counts smartloc truth times from the first epoch, ``time_gps_s[0]``.
    """
    time_gps_s = np.asarray(time_gps_s, dtype=float)
    guessed = spec.time_origin_gps_s is None and spec.truth_format == "smartloc"
    if spec.time_origin_gps_s is None:
        spec = replace(spec, time_origin_gps_s=float(time_gps_s[0]) if time_gps_s.size else 0.0)
    try:
        t_truth, xyz, bad = _sorted_truth_rows(spec, spec.time_origin_gps_s)
    except InputError as err:
        other = _readable_as(spec.truth, spec.truth_format)
        if other is None:
            columns = TRUTH_COLUMNS.get(spec.truth_format)
            if columns is None or not err.reason.startswith("no readable ground-truth line"):
                raise
            raise InputError(err.path, f"{err.reason} (truth format {spec.truth_format!r} has rows of {columns})",
                             line=err.line) from None
        give = f'format = "{other}" in [truth] of {spec.source}' if spec.source else f"--truth-format {other}"
        raise InputError(err.path, f"{err.reason} (read as truth format {spec.truth_format!r}; the file reads as "
                                   f"{other!r}: give {give})", line=err.line) from None
    if spec.truth_format == "static":
        return np.broadcast_to(xyz[0], (time_gps_s.size, 3)).copy(), bad
    truth = _truth_at(time_gps_s, t_truth, xyz, spec.match_tolerance_s)
    ok = np.isfinite(truth).all(axis=1)
    inside = (time_gps_s >= t_truth[0]) & (time_gps_s <= t_truth[-1])
    if guessed and inside.sum() >= 10 and ok[inside].mean() < 0.9:
        # smartloc truth is stamped at the receiver's epochs: a right origin matches nearly every epoch it spans
        warnings.warn(f"{spec.truth}: only {int(ok[inside].sum())} of {int(inside.sum())} epochs within the truth's "
                      f"time span match a truth time when its t = 0 is taken as the first epoch given (GPS "
                      f"{spec.time_origin_gps_s:.1f} s){_given_shift_words(spec.time_offset_s)}; if these epochs do "
                      "not start where the truth does, give the GPS time of its t = 0 (time_origin_gps_s, "
                      "--truth-origin)",
                      stacklevel=3)
    return truth, bad


def _given_shift_words(time_offset_s: float) -> str:
    """The truth's shift [s] in words, `` and its times shifted by +2 s (time_offset_s, ...)``; empty for 0."""
    return f" and its times shifted by {time_offset_s:+g} s (time_offset_s, --truth-offset)" if time_offset_s else ""


def _sorted_truth_rows(spec: DatasetSpec, first_epoch_gps_s: float) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """A truth file's rows in time order: times [GPS s] (a smartloc file's counted from ``spec.time_origin_gps_s``,
    else from ``first_epoch_gps_s``), ECEF [m], and the reader's notes."""
    origin = first_epoch_gps_s if spec.time_origin_gps_s is None else spec.time_origin_gps_s
    t_truth, xyz, bad = TRUTH_READERS[spec.truth_format](spec.truth, replace(spec, time_origin_gps_s=float(origin)))
    t_truth = t_truth + spec.time_offset_s
    order = np.argsort(t_truth, kind="stable")
    t_truth, xyz = t_truth[order], xyz[order]
    repeat = np.flatnonzero(np.diff(t_truth) <= 1e-6)      # row repeat + 1 has row repeat's time
    if repeat.size:
        apart = np.linalg.norm(xyz[repeat + 1] - xyz[repeat], axis=1)
        if (apart > TRUTH_REPEAT_M).any():
            j = int(np.argmax(apart > TRUTH_REPEAT_M))
            week, tow = gps_s_to_week_tow(t_truth[repeat[j]])
            raise InputError(spec.truth, f"{int((apart > TRUTH_REPEAT_M).sum())} row(s) repeat another row's time with "
                                         f"another position (first at GPS week {int(week)} {float(tow):.3f} s, "
                                         f"{float(apart[j]):.1f} m apart): which one is the truth? Remove the repeats")
        keep = np.ones(t_truth.size, bool)
        keep[repeat + 1] = False                            # the same point twice: once is enough
        t_truth, xyz = t_truth[keep], xyz[keep]
    return t_truth, xyz, bad


def _truth_at(time_gps_s: np.ndarray, t_truth: np.ndarray, xyz: np.ndarray, tolerance_s: float) -> np.ndarray:
    """(T, 3) truth [m] at epoch times [s] from rows sorted by time (``interpolate_truth``); NaN where no row lies
    within ``tolerance_s``."""
    right = np.clip(np.searchsorted(t_truth, time_gps_s), 0, t_truth.size - 1)
    left = np.clip(right - 1, 0, t_truth.size - 1)
    nearest = np.where(np.abs(t_truth[left] - time_gps_s) <= np.abs(t_truth[right] - time_gps_s), left, right)
    ok = np.abs(t_truth[nearest] - time_gps_s) <= tolerance_s
    return np.where(ok[:, None], interpolate_truth(time_gps_s, t_truth, xyz, left, right, nearest), np.nan)


def interpolate_truth(time_gps_s: np.ndarray, t_truth: np.ndarray, xyz: np.ndarray, left: np.ndarray,
                      right: np.ndarray, nearest: np.ndarray) -> np.ndarray:
    """(T, 3) truth [m] at epoch times [s]: linear in time between the rows bracketing each epoch, else the nearest row.

    Rows are sorted by time; ``left``/``right`` index the rows before and after each epoch, ``nearest`` the closer.
    An epoch is interpolated only when it lies between two rows at most ``TRUTH_INTERPOLATION_MAX_GAP_S`` apart, so
    a gap in the truth is never bridged. Between rows dt apart the nearest row is off by up to v dt / 2 (2.5 m at 5 m/s
    with 1 Hz truth), the interpolation by at most a dt^2 / 8 (decimetres in a turn).
    """
    t_left, t_right = t_truth[left], t_truth[right]
    span = t_right - t_left
    between = (t_left <= time_gps_s) & (time_gps_s <= t_right) & (span > 0) & (span <= TRUTH_INTERPOLATION_MAX_GAP_S)
    weight = np.where(between, (time_gps_s - t_left) / np.where(between, span, 1.0), 0.0)[:, None]
    return np.where(between[:, None], (1.0 - weight) * xyz[left] + weight * xyz[right], xyz[nearest])


# -- building and splitting ---------------------------------------------------------------------------------

def _fingerprint(spec: DatasetSpec, feature_names: tuple[str, ...]) -> str:
    """Cache key of a built dataset: its files' bytes, its settings and the versions of the readers that built it."""
    from . import navigation, rinex      # lazily, as build() does; a reader's change reaches the datasets it built

    h = hashlib.sha256()
    for p in spec.files():
        h.update(p.read_bytes())
    h.update(json.dumps([_BUILD_VERSION, rinex._PARSER_VERSION, navigation._CACHE_VERSION, spec.id,
                         list(feature_names), spec.systems, spec.truth_format,
                         spec.match_tolerance_s, spec.time_origin_gps_s,
                         *([spec.time_offset_s] if spec.time_offset_s else [])]).encode())
    return h.hexdigest()[:24]


def join_observations(parts: list[Observations]) -> Observations:
    """The epochs of several observation files of one receiver, in time order; files overlapping in time are refused."""
    from .observations import Observations

    parts = sorted(parts, key=lambda o: o.time_gps_s[0])
    for before, after in zip(parts, parts[1:]):
        if after.time_gps_s[0] <= before.time_gps_s[-1]:
            raise InputError(after.path, f"overlaps {before.path} in time (GPS {after.time_gps_s[0]:.1f} s to "
                                         f"{after.time_gps_s[-1]:.1f} s against {before.time_gps_s[0]:.1f} s to "
                                         f"{before.time_gps_s[-1]:.1f} s); observation files are joined in time "
                                         f"order and must not overlap")
        for system in set(before.codes) & set(after.codes):
            if before.codes[system] != after.codes[system]:
                raise InputError(after.path, f"{system} pseudoranges are {after.codes[system]}, in {before.path} "
                                             f"{before.codes[system]}; observation files joined must use one signal")
    sv = np.unique(np.concatenate([o.sv for o in parts]))
    n_t = sum(len(o) for o in parts)
    arrays = {key: np.full((n_t, sv.size), np.nan) for key in ("pr_m", "cn0_dbhz", "doppler_hz")}
    start = 0
    for o in parts:
        rows, cols = slice(start, start + len(o)), np.searchsorted(sv, o.sv)
        for key, joined in arrays.items():
            joined[rows, cols] = getattr(o, key)
        start += len(o)
    return Observations(" + ".join(o.path for o in parts), parts[0].version,
                        np.concatenate([o.time_gps_s for o in parts]), sv,
                        codes={k: v for o in parts for k, v in o.codes.items()}, approx_ecef_m=parts[0].approx_ecef_m,
                        warnings=tuple(w for o in parts for w in o.warnings), **arrays)


def truth_note_summary(truth_path: str | Path, notes: list[str]) -> list[str]:
    """The truth reader's notes as shown to a user: the first five, then a count of them all."""
    more = [f"{truth_path}: {len(notes)} unreadable truth lines skipped in all"] if len(notes) > 5 else []
    return notes[:5] + more


def _warn_truth(spec: DatasetSpec, seq: Sequence, notes: list[str]) -> None:
    """Warn of skipped truth lines (``truth_note_summary``), of a truth that does not fit the coarse fixes
    (``truth_fit_notes``) and of a truth that labels no epoch."""
    for note in truth_note_summary(spec.truth, notes) + truth_fit_notes(spec, seq.time_gps_s, seq.truth_ecef_m,
                                                                         seq.coarse_ecef_m):
        warnings.warn(f"dataset {spec.id}: {note}", stacklevel=3)
    if not seq.labelled.any():
        origin = " and [truth] time_origin_gps_s (GPS seconds of its t = 0)" if spec.truth_format == "smartloc" else ""
        warnings.warn(f"dataset {spec.id}: no truth time in {spec.truth} lies within {spec.match_tolerance_s:g} s of "
                      f"an epoch of {', '.join(map(str, spec.obs))}; check [truth] format = {spec.truth_format!r}, "
                      f"match_tolerance_s{origin}{unmatched_time_words(spec, seq.time_gps_s)}", stacklevel=3)


def build(dataset_id: str, *, feature_names: tuple[str, ...] = DEFAULT_FEATURES, cache: bool = True) -> Sequence:
    """The whole dataset as one Sequence with aligned truth, built once and cached by content.

    Several obs files are joined in time order (``join_observations``). Skipped truth lines, a truth that
    labels no epoch and a constellation of ``systems`` with no usable observation are reported as warnings.
    """
    from .features import build_sequence, check_feature_names
    from .measurements import load
    from .rinex import load_obs
    from .spp import spp

    spec = get(dataset_id)
    missing = spec.missing()
    if missing:
        note = spec.missing_note() if spec.source else \
            f"missing {', '.join(map(str, missing))}{shared_data_hint(missing[0])}"
        raise FileNotFoundError(f"dataset {dataset_id}: {note}")
    feature_names = check_feature_names(feature_names)
    target = cache_file("sequences", f"{dataset_id}-{_fingerprint(spec, feature_names)}.npz") if cache else None
    seq = load_cached(target, load_sequence)
    if seq is not None:
        notes = align_truth(seq.time_gps_s, spec)[1]    # a cached build warns as the first one did
    else:
        obs = spec.obs[0] if len(spec.obs) == 1 else join_observations([load_obs(p) for p in spec.obs])
        with warnings.catch_warnings():     # said below for cached builds too, in one warning
            warnings.filterwarnings("ignore", r".*: no [A-Z] observations \(requested\)")
            meas = load(obs, spec.nav, systems=spec.systems)
        fix = spp(meas)
        truth, notes = align_truth(meas.time_gps_s, spec)
        seq = build_sequence(meas, fix, feature_names=feature_names, name=dataset_id, truth_ecef_m=truth)
        store_cached(target, lambda tmp: save_sequence(tmp, seq))
    _warn_truth(spec, seq, notes)
    dropped = [c for c in spec.systems or () if c not in seq.systems]
    if dropped:
        warnings.warn(f"dataset {dataset_id}: constellation(s) {''.join(dropped)} of its systems have no usable "
                      f"observation and are left out (its observation files hold none, or its navigation files lack "
                      f"their ephemerides): the sequence has {''.join(seq.systems)}", stacklevel=2)
    return seq


def split_parts(split: str) -> tuple[str, ...]:
    """The split names in ``split``: ``"train+val"`` is both (their union), ``"train"`` itself."""
    return tuple(split.split("+"))


def split_index(seq: Sequence, spec: DatasetSpec, split: str) -> np.ndarray:
    """(T,) bool: epochs of ``seq`` in the split (only labelled epochs count for 'epoch' axes); "a+b": in a or b."""
    if "+" in split and split not in spec.splits:
        return np.logical_or.reduce([split_index(seq, spec, part) for part in split_parts(split)])
    check_split(spec, split)
    start, stop = spec.splits[split]
    axis = split_axis_values(seq, spec)
    return seq.labelled & (axis >= start) & (axis < stop)


def check_split(spec: DatasetSpec, split: str) -> None:
    """UnknownNameError (a KeyError of one line) unless ``spec`` has each split named in ``split`` ("a+b": a and b)."""
    for part in [split] if split in spec.splits else split_parts(split):
        if part not in spec.splits:
            where = f"; give {part} = [start, stop] under [splits] in {spec.source}" if spec.source else ""
            raise UnknownNameError(f"dataset {spec.id} has no split {part!r}{did_you_mean(part, list(spec.splits))}; "
                                   f"it has {', '.join(spec.splits) or 'none'}{where}")


def obs_hashes(dataset_id: str) -> set[str]:
    """SHA-256 (16 hex digits) of a dataset's observation files, of their content and of their bytes (older model
    records hashed a ``.gz`` file's bytes; ``lfgnss.paths.file_hashes``)."""
    return file_digests(get(dataset_id).obs)


def epochs_in_split(dataset_id: str, split: str, time_gps_s: np.ndarray) -> int | None:
    """How many of the epoch times [GPS s] lie in a split of the dataset registered as ``dataset_id`` now, read from its
    bounds alone; None when that needs its data (an ``epoch`` axis, a ``relative_s`` one without a time origin, a
    ``tow`` split past 604800 s, whose week is the dataset's first epoch's) or no such dataset or split is registered.
    For epochs of that dataset's own files (a model file's record)."""
    spec = registered().get(dataset_id)
    bounds = [spec.splits.get(part) for part in split_parts(split)] if spec else [None]
    if None in bounds or spec.split_axis not in ("tow", "relative_s"):
        return None
    if spec.split_axis == "relative_s" and spec.time_origin_gps_s is None:
        return None                                 # counted from the dataset's first epoch, which needs its data
    bounds_s = [b for pair in bounds for b in pair if math.isfinite(b)]
    if spec.split_axis == "tow" and any(b > SECONDS_PER_WEEK for b in bounds_s):
        return None                                 # a split in the next week: which week is the first epoch's
    time_gps_s = np.asarray(time_gps_s, float)
    if spec.split_axis == "tow":                    # within one week: each epoch's own time of week
        axis = np.round(gps_s_to_week_tow(time_gps_s)[1], 1)
    else:
        axis = _time_axis_values(time_gps_s, spec, spec.time_origin_gps_s)
    return int(sum(np.sum((axis >= start) & (axis < stop)) for start, stop in bounds))


def split_bounds_words(spec: DatasetSpec, split: str) -> str:
    """``val = [150, 180)`` for each part of ``split`` that ``spec`` has (bounds on its axis), joined by commas."""
    return ", ".join(f"{part} = [{spec.splits[part][0]:.10g}, {spec.splits[part][1]:.10g})"
                     for part in split_parts(split) if part in spec.splits)


def empty_split_words(seq: Sequence, spec: DatasetSpec, split: str) -> str:
    """Why ``split`` of ``seq`` has no labelled epoch, in words: its bounds, and where the labelled epochs lie on its
    axis."""
    span = split_axis_values(seq, spec)[seq.labelled]
    bounds = split_bounds_words(spec, split)
    where = (f"the labelled epochs span [{span.min():.10g}, {span.max():.10g}] on it" if span.size
             else "no epoch has truth")
    return f"[splits] axis = {spec.split_axis!r}, {bounds} holds no labelled epoch of dataset {spec.id} ({where})"


def split_axis_values(seq: Sequence, spec: DatasetSpec) -> np.ndarray:
    """(T,) each epoch's place on ``spec``'s split axis: time of week [s] (of the first epoch's week, past 604800 s in
    the next one), seconds since the truth origin [s] (both to 0.1 s), or the index among labelled epochs (-1 for an
    unlabelled one). ``seq`` needs only ``time_gps_s`` and ``labelled`` (benchmarks/front_end.py passes such a
    stand-in)."""
    if spec.split_axis in ("tow", "relative_s"):
        return _time_axis_values(seq.time_gps_s, spec, seq.time_gps_s[0] if np.size(seq.time_gps_s) else 0.0)
    if spec.split_axis == "epoch":
        labelled = seq.labelled
        return np.where(labelled, np.cumsum(labelled) - 1, -1)
    raise ValueError(f"dataset {spec.id}: unknown split axis {spec.split_axis!r}")


def _time_axis_values(time_gps_s: np.ndarray, spec: DatasetSpec, first_epoch_gps_s: float) -> np.ndarray:
    """Epoch times [GPS s] on a ``tow`` or ``relative_s`` split axis, to 0.1 s: the seconds since the start of the GPS
    week of ``first_epoch_gps_s`` (its time of week, counting on past 604800 s so that a drive across a week's end
    keeps one axis), or the seconds since ``spec.time_origin_gps_s`` (else since ``first_epoch_gps_s``)."""
    if spec.split_axis == "tow":
        week_start = np.floor(first_epoch_gps_s / SECONDS_PER_WEEK) * SECONDS_PER_WEEK
        return np.round(np.asarray(time_gps_s, float) - week_start, 1)
    return np.round(time_gps_s - _relative_origin_gps_s(spec, first_epoch_gps_s), 1)


def _relative_origin_gps_s(spec: DatasetSpec, first_epoch_gps_s: float) -> float:
    """What a ``relative_s`` split axis counts from [GPS s]: ``spec.time_origin_gps_s``, else the first epoch."""
    return first_epoch_gps_s if spec.time_origin_gps_s is None else spec.time_origin_gps_s


def present(dataset_ids, report=print) -> list[str]:
    """The ids whose files are all there; ``report`` gets one "ID: skipped, missing PATH" line for each other
    (``DatasetSpec.missing_note``: with the key and TOML file naming it for a registered one)."""
    ids = []
    for dataset_id in dataset_ids:
        note = get(dataset_id).missing_note()
        if note:
            report(f"{dataset_id}: skipped, {note}")
        else:
            ids.append(dataset_id)
    return ids


def contiguous_runs(index: np.ndarray) -> list[np.ndarray]:
    """The unbroken runs (consecutive integers) of a sorted index array."""
    return [r for r in np.split(index, np.flatnonzero(np.diff(index) > 1) + 1) if r.size]


def split_pieces(seq: Sequence, spec: DatasetSpec, split: str) -> list[np.ndarray]:
    """The split's labelled epochs of ``seq`` in pieces, each run from a labelled epoch of the split to the next one
    unless a labelled epoch of no part of it lies between: epochs without truth inside (a gap in the truth, a truth
    file slower than the receiver) stay in a piece, solved and not scored, rather than cutting it."""
    inside = split_index(seq, spec, split)
    idx = np.flatnonzero(inside)
    others = np.cumsum(seq.labelled & ~inside)         # labelled epochs not in the split, counted up to each epoch
    return [r for r in np.split(idx, np.flatnonzero(np.diff(others[idx]) > 0) + 1) if r.size]


def load_split(dataset_id: str, split: str, *, feature_names: tuple[str, ...] = DEFAULT_FEATURES,
               cache: bool = True) -> list[Sequence]:
    """The split as Sequences (one per piece, ``split_pieces``: from a first to a last labelled epoch, the epochs
    between included); "train+val": the two splits'."""
    spec = get(dataset_id)
    check_split(spec, split)                # before the build, which can take minutes
    seq = build(dataset_id, feature_names=feature_names, cache=cache)
    runs = split_pieces(seq, spec, split)
    return [seq.subset(slice(r[0], r[-1] + 1), name=f"{dataset_id}/{split}" + (f"#{k}" if len(runs) > 1 else ""))
            for k, r in enumerate(runs)]


__all__ = ["DatasetSpec", "SPLITS", "align_truth", "build", "contiguous_runs", "find_dataset_toml", "get",
           "load_split", "present", "register", "register_toml", "registered", "split_index", "split_parts",
           "split_pieces", "static_time_note", "truth_note_summary"]


def alignment_report(dataset_ids: list[str] | None = None, problems: list[str] | None = None) -> str:
    """Matched epochs per split and the coarse-fix error distribution, as plain text; ``problems`` (a list) gets one
    line per dataset without truth and per empty split."""
    from .metrics import accuracy_table

    lines, problems = [], [] if problems is None else problems
    for dataset_id in present(dataset_ids or sorted(_builtin()), lines.append):
        spec = get(dataset_id)
        seq = build(dataset_id)
        labelled = seq.labelled
        lines.append(f"{dataset_id}: {len(seq)} epochs, {int(labelled.sum())} with truth; systems "
                     f"{''.join(seq.systems)}" + (f"; {spec.description}" if spec.description else ""))
        if not labelled.any():
            problems.append(f"{dataset_id}: no epoch has truth")
        for split in spec.splits:
            idx = split_index(seq, spec, split)
            if not idx.any():
                lines.append(f"  {split:5s}     0 matched epochs ({empty_split_words(seq, spec, split)})")
                if labelled.any():
                    problems.append(f"{dataset_id}: its {split} split has no epoch with truth")
                continue
            has_fix = np.all(np.isfinite(seq.coarse_ecef_m), axis=1)
            row = accuracy_table(seq.coarse_ecef_m[idx], seq.truth_ecef_m[idx], has_fix[idx])
            first, last = gpst_stamp(seq.time_gps_s[idx].min(), 1), gpst_stamp(seq.time_gps_s[idx].max(), 1)
            since = (f", seconds since {gpst_stamp(_relative_origin_gps_s(spec, seq.time_gps_s[0]), 1)}"
                     if spec.split_axis == "relative_s" else "")
            lines.append(f"  {split:5s} {int(idx.sum()):5d} matched epochs, {first} to "
                         f"{last[11:] if last[:10] == first[:10] else last} GPST ({split_bounds_words(spec, split)} "
                         f"on axis {spec.split_axis!r}{since})")
            lines.append(f"{'':17s}coarse fix for {row['availability']:.1%}: "
                         f"3D RMSE {row['rmse_3d_m']:.1f} m, 2D RMSE {row['rmse_2d_m']:.1f} m, "
                         f"3D p50 {row['p50_3d_m']:.1f} m, p95 {row['p95_3d_m']:.1f} m")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """``python -m lfgnss.datasets [ID ...]``: build datasets and print the alignment report.

    Bad input (a config, an id, a file) ends in one line ``error: ...`` and exit code 2, as does a dataset
    asked for by id or ``--register`` whose files are missing (a registered one is left out of the report: the
    error line names its TOML file), and one reported without truth or with a split of no labelled epoch (after the
    report); the default benchmark sets are skipped quietly.
    """
    import argparse
    import sys

    from .errors import INPUT_ERRORS, one_line

    parser = argparse.ArgumentParser(prog="python -m lfgnss.datasets", description=main.__doc__.split("\n")[0],
                                     formatter_class=PlainHelp)
    parser.add_argument("ids", nargs="*", help=f"dataset ids (default: {', '.join(sorted(_builtin()))})")
    parser.add_argument("--register", action="append", default=[], metavar="TOML", help="user dataset config")
    args = parser.parse_args(argv)
    warnings.simplefilter("ignore", FutureWarning)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", UserWarning)
            ids = list(dict.fromkeys([*args.ids, *(register_toml(path).id for path in args.register)]))
            unbuilt = [f"{i}: {get(i).missing_note()}" for i in ids if get(i).missing()]
            shown = [i for i in ids if get(i).source is None or not get(i).missing()]
            problems: list[str] = []
            report = alignment_report(shown or None, problems) if shown or not ids else ""
        for message in dict.fromkeys(str(w.message) for w in caught):
            print(f"warning: {message}", file=sys.stderr)
        if report:
            print_stdout(report)
        if unbuilt:
            print(f"error: dataset not built: {'; '.join(unbuilt)}", file=sys.stderr)
        if problems:                # what the training and benchmark commands would refuse
            print(f"error: {'; '.join(problems)} (see above)", file=sys.stderr)
        return 2 if unbuilt or problems else 0
    except INPUT_ERRORS as err:
        print(f"error: {one_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:   # a cache entry is written whole or not at all: the next run builds what is missing
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # a bug, not bad input: still one line, no traceback, a distinct exit code
        print(f"error: internal error while building datasets ({type(err).__name__}: {one_line(err)}); "
              f"please report it", file=sys.stderr)
        return 3


if __name__ == "__main__":
    raise SystemExit(main())
