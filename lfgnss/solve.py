"""``python -m lfgnss.solve``: position a receiver from RINEX with an LF-GNSS estimator.

With no arguments it runs the EKF with the bundled model on the bundled Berlin sample and prints the
accuracy against its ground truth. Errors in the input end the run with one line naming the file and
a non-zero exit code; every output already written stays.
"""
from __future__ import annotations

import argparse
import datetime as dt
import math
import re
import sys
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .constants import SYSTEMS, unknown_systems
from .errors import (INPUT_ERRORS, InputError, LfgnssError, RinexError, cannot_write, one_line, path_option,
                     stdout_gone)
from .help_text import PlainHelpWithDefaults
from .observations import Observations
from .paths import bundled_data_dir, bundled_models, default_model_path, make_output_folder, model_path
from .spp import SppConfig
from .time import SECONDS_PER_WEEK, datetime64_to_gps_s, gps_s_to_week_tow, gpst_stamp, week_tow_to_gps_s

if TYPE_CHECKING:
    from estimators.base import Solution

    from .measurements import Measurements
    from .spp import CoarseFix

SAMPLE_DIR = bundled_data_dir() / "berlin-potsdamer-platz"
SAMPLE_OBS = SAMPLE_DIR / "Berlin_Potsdamer_Platz.obs.gz"
SAMPLE_NAV = (SAMPLE_DIR / "brdc1580.16n.gz", SAMPLE_DIR / "brdc1580.16g.gz")
SAMPLE_TRUTH = SAMPLE_DIR / "Berlin_Potsdamer_Platz_GT.txt"
DEFAULT_MODEL = default_model_path()
LEARNED_BACKENDS = ("ekf", "fgo")
SMOOTHABLE_BACKENDS = ("ekf", "plain-ekf")
PROGRESS_BACKENDS = ("ekf", "plain-ekf", "fgo")   # a tqdm bar over the epochs on a terminal
COMPRESSION_SUFFIXES = (".gz", ".z", ".bz2", ".xz", ".zip")    # lower case; .Z (compress) among them
#: The elevation mask of the coarse fix, quality control and features [deg], and of the bundled models' training data.
DEFAULT_ELEVATION_MASK_DEG = SppConfig().elevation_mask_deg
#: --start/--end take epochs this close outside the window [s] (RTKLIB's DTTOL: receivers tag epochs ms early).
WINDOW_TOLERANCE_S = 0.025
#: Input notes shown before the accuracy table (then a count of them all).
NOTES_SHOWN = 5
_SYSTEM_SEPARATORS = re.compile(r"[\s,]+")
_WEEK_TOW = re.compile(r"\s*(\d{1,4}):(\d+(?:\.\d*)?)\s*")
_CALENDAR = re.compile(r"\s*(\d{4})[/-](\d{1,2})[/-](\d{1,2})(?:\s+|T)(\d{1,2}):(\d{1,2}):(\d{1,2}(?:\.\d*)?)\s*")


class _HelpFormatter(PlainHelpWithDefaults):
    """Shows a default only where there is one to show (not None, not a flag's False)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        if action.default is None or action.default is False or "default:" in (action.help or ""):
            return action.help or ""
        return super()._get_help_string(action)


def build_parser() -> argparse.ArgumentParser:
    """The command-line interface of ``python -m lfgnss.solve``."""
    import estimators

    from .datasets import TRUTH_COLUMNS, TRUTH_READERS

    p = argparse.ArgumentParser(prog="python -m lfgnss.solve", description=__doc__.split("\n\n")[0],
                                formatter_class=_HelpFormatter)
    backends = estimators.available()
    p.add_argument("--backend", default="ekf", choices=backends, help="estimator plug-in, in any case",
                   type=lambda text: next((name for name in backends if name.lower() == text.lower()), text))
    p.add_argument("--obs", type=path_option, nargs="+",
                   help="RINEX observation file(s) of one receiver, e.g. hourly files, joined in time order (default: "
                        "the bundled Berlin sample); outputs are named after the first")
    p.add_argument("--nav", type=path_option, nargs="+",
                   help="RINEX navigation file(s) (default: the bundled sample's, with no --obs)")
    p.add_argument("--model", type=path_option, help="LF-GNSS model file, or a bundled model's name: "
                   f"{', '.join(bundled_models())} (default: default, trained on all three benchmark datasets)")
    p.add_argument("--no-model", action="store_true", help="use the hand-set C/N0 noise model instead")
    p.add_argument("--systems", type=_systems, default=None,
                   help=f"constellations to use, letters of {''.join(SYSTEMS)}: GC, \"G C\" or G,C "
                        "(default: all present)")
    p.add_argument("--truth", type=path_option, help="ground-truth file, for an accuracy table and error plots")
    p.add_argument("--truth-format", type=str.lower, default=None, choices=tuple(TRUTH_READERS),
                   help="format of the --truth file, in any case (default: urbannav; with no --truth and no --obs, "
                        "the bundled sample's smartloc truth). Rows of " + "; ".join(
                            f"{name}: {columns}" for name, columns in TRUTH_COLUMNS.items()))
    p.add_argument("--truth-origin", type=_finite_float, default=None,
                   help="GPS seconds of t=0 for smartloc truth (default: first epoch)")
    p.add_argument("--truth-offset", type=_finite_float, default=None, metavar="SECONDS",
                   help="seconds added to the --truth file's times as read: 18 for a truth stamped in UTC "
                        "(2017-2026), -28782 for one in UTC+8 local time (default 0)")
    p.add_argument("--start", type=_gps_time, default=None, metavar="TIME",
                   help='first epoch to solve, GPST: WEEK:TOW (1900:126700.5) or "YYYY/MM/DD HH:MM:SS" (rnx2rtkp -ts)')
    p.add_argument("--end", type=_gps_time, default=None, metavar="TIME",
                   help="last epoch to solve, inclusive, in the same forms (rnx2rtkp -te)")
    p.add_argument("--elevation-mask", type=_elevation_mask, default=DEFAULT_ELEVATION_MASK_DEG, metavar="DEG",
                   help="elevation mask of the coarse fix, quality control and features [deg]")
    p.add_argument("--mode", default=None, choices=("batch", "fixed-lag"),
                   help="fgo mode: batch, the whole run in one graph (default), or fixed-lag, a causal sliding "
                        "10 s window, less accurate than either batch or ekf on the bundled drive (README)")
    p.add_argument("--smooth", action="store_true",
                   help="ekf, plain-ekf: smooth the filter's run backwards (Rauch-Tung-Striebel; post-processing)")
    p.add_argument("--smooth-lag", type=_finite_float, default=None, metavar="SECONDS",
                   help="with --smooth: a fixed-lag smoother, each epoch using the epochs up to SECONDS later")
    p.add_argument("--marginals", action="store_true",
                   help="fgo: write the graph's marginal sds, inflated by its pseudorange residuals as the EKF's, "
                        "not the default per-epoch least-squares stand-in, which can reach kilometres where few "
                        "satellites are seen (docs/sd_consistency.md)")
    p.add_argument("--formal-sd", action="store_true",
                   help="ekf, plain-ekf, fgo --marginals: write the formal sds, not those inflated by the pseudorange "
                        "residuals (docs/sd_consistency.md)")
    p.add_argument("--out", type=path_option, default=Path("lfgnss-out"), help="output folder")
    p.add_argument("--points", action="store_true",
                   help="also write each epoch as a point in the GeoJSON and KML, with its time (UTC), status and "
                        "satellites used (Google Earth's time slider reads them)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--quiet", action="store_true", help="print only the accuracy table")
    return p


def _noise(args):
    """The noise model for the backend: the model file, or the heuristic one (with the reason)."""
    from estimators.noise import HeuristicNoise

    if args.backend not in LEARNED_BACKENDS:
        return None, "hand-set C/N0 noise" if args.backend != "wls" else "equal weights"
    if args.no_model:
        return HeuristicNoise(), "hand-set C/N0 noise"
    path = args.model or DEFAULT_MODEL
    if args.model is None and not path.exists():
        return HeuristicNoise(), "hand-set C/N0 noise (no bundled model found)"
    from learning.export import load_model, trained_smoothed, untrained_reason

    from .features import AVAILABLE_FEATURES

    model = load_model(path)
    if trained_smoothed(model.metadata) and args.backend == "ekf" and not args.smooth:
        warnings.warn(f"{model_path(path)}: trained and selected on RTS-smoothed positions (train.smooth = true); "
                      f"this run filters forward only: add --smooth to run it as it was trained")
    untrained = untrained_reason(model)
    if untrained is not None:
        warnings.warn(f"{model_path(path)}: {untrained}; --no-model runs the hand-set noise instead")
    unknown = [n for n in model.feature_names if n not in AVAILABLE_FEATURES]
    if unknown:
        raise InputError(path, f"the model needs feature(s) {', '.join(unknown)} that this lfgnss cannot compute "
                               f"(it computes {', '.join(AVAILABLE_FEATURES)})")
    return model, f"model {model_path(path)}"


#: The coarse least-squares fix's name in the accuracy table and the figures.
COARSE_LABEL = "least squares (coarse)"


def seen_epochs_notes(noise: object, obs: str | Path | list, time_gps_s: np.ndarray, truth_ecef_m: np.ndarray
                      ) -> list[str]:
    """Where a learned model was trained or selected on epochs this run scores (``learning.export.seen_test_epochs``:
    its recorded training pieces by time and place, else its datasets' observation files by content): one line
    each, the accuracy table then being in-sample on them; [] for hand-set noise or none. ``obs``: the run's
    observation file, or its files."""
    from learning.export import seen_test_epochs

    from .paths import file_digests

    meta = getattr(noise, "metadata", None)
    if not isinstance(meta, dict):
        return []
    scored = np.isfinite(truth_ecef_m).all(axis=1)
    files = list(obs) if isinstance(obs, (list, tuple)) else [obs]
    return seen_test_epochs(meta, file_names(files), time_gps_s[scored], truth_ecef_m[scored], file_digests(files),
                            epochs_word="scored epochs")


def file_names(paths: list) -> str:
    """``a.obs + b.obs``: the names of a run's observation files."""
    return " + ".join(Path(f).name for f in paths)


def unseen_systems_note(noise: object, systems: tuple[str, ...]) -> str | None:
    """Words for a learned model that never saw some of ``systems`` (constellation letters) in training, or None
    (hand-set noise, a model file that does not record its data's constellations, or nothing unseen)."""
    from learning.export import trained_systems

    from .constants import SYSTEM_NAMES

    seen = trained_systems(getattr(noise, "metadata", None) or {})
    unseen = [c for c in systems if seen is not None and c not in seen]
    if not unseen:
        return None
    names = " and ".join(SYSTEM_NAMES.get(c, c) for c in unseen)
    kept = "".join(c for c in systems if c in seen)
    what = "those constellations" if len(unseen) > 1 else "that constellation"
    return (f"trained on {''.join(seen)} data only; this run's {names} satellites get R and v^c from a network that "
            f"never saw {what}" + (f" (--systems {kept} leaves them out)" if kept else ""))


@dataclass
class _Solved:
    """What a run solved and wrote, for its summary."""

    obs: str                          # the observation file, or files joined by " + "
    keep: np.ndarray                  # (T,) bool: the file's epochs that were solved
    meas: Measurements                # of the solved epochs
    fix: CoarseFix
    solution: Solution
    truth: np.ndarray | None          # (T', 3) ECEF [m] of the solved epochs, NaN where none; None: no table
    label: str                        # the estimator's row in the table
    noise_text: str
    written: list[str | Path]
    failed: list[str]                 # one-line messages of outputs that could not be written


def run(args) -> int:
    """Solve, write outputs, print the summary; returns the exit code."""
    _check_options(args)
    with warnings.catch_warnings(record=True) as caught:   # shown in the summary, once each
        warnings.simplefilter("always", UserWarning)
        solved = _solve(args)
    try:                      # stdout may be a pipe closed early (| head): the files are written by now
        _print_summary(args, solved, [str(w.message) for w in caught])
        sys.stdout.flush()
    except BrokenPipeError:   # nothing more to say on stdout; the errors below still reach stderr
        stdout_gone()
    for message in solved.failed:
        print(f"error: {message}", file=sys.stderr)
    return 2 if solved.failed else 0


def _check_options(args) -> None:
    """ValueError for options that do not apply or contradict each other, before any file is read."""
    if args.smooth_lag is not None and args.backend not in SMOOTHABLE_BACKENDS:
        raise ValueError(f"--smooth-lag applies to --backend {' and '.join(SMOOTHABLE_BACKENDS)} with --smooth, not "
                         f"{args.backend}" + (" (its fixed-lag mode: --mode fixed-lag)" if args.backend == "fgo" else ""))
    if args.smooth_lag is not None and not args.smooth:
        raise ValueError(f"--smooth-lag needs --smooth (--smooth --smooth-lag {args.smooth_lag:g})")
    if args.smooth_lag is not None and args.smooth_lag < 0:
        raise ValueError(f"--smooth-lag must be a lag >= 0 seconds, got {args.smooth_lag:g}")
    if args.smooth and args.backend not in SMOOTHABLE_BACKENDS:
        raise ValueError(f"--smooth applies to --backend {' and '.join(SMOOTHABLE_BACKENDS)}, not {args.backend}"
                         + (" (the factor graph's batch mode already uses every epoch)" if args.backend == "fgo" else ""))
    if args.marginals and args.backend != "fgo":
        raise ValueError(f"--marginals applies to --backend fgo, not {args.backend}")
    if args.formal_sd and args.backend not in SMOOTHABLE_BACKENDS and not args.marginals:
        which = ("fgo's default stand-in (add --marginals)" if args.backend == "fgo"
                 else f"{args.backend} (whose sds are not inflated)")
        raise ValueError(f"--formal-sd applies to --backend {' and '.join(SMOOTHABLE_BACKENDS)} and to fgo with "
                         f"--marginals, not {which}")
    if (args.model is not None or args.no_model) and args.backend not in LEARNED_BACKENDS:
        raise ValueError(f"--{'model' if args.model is not None else 'no-model'} applies to --backend "
                         f"{' and '.join(LEARNED_BACKENDS)}, not {args.backend} (which has no learned noise)")
    if args.model is not None and args.no_model:
        raise ValueError("--model and --no-model contradict each other")
    if args.mode is not None and args.backend != "fgo":
        raise ValueError(f"--mode applies to --backend fgo, not {args.backend}")
    if args.start is not None and args.end is not None and args.end < args.start:
        raise ValueError(f"--end {_gpst_text(args.end)} is before --start {_gpst_text(args.start)}")
    if args.obs is None and args.nav:
        raise ValueError("--nav needs --obs (without --obs the bundled sample is solved with its own navigation files)")
    for option, value in (("--truth-format", args.truth_format), ("--truth-origin", args.truth_origin),
                          ("--truth-offset", args.truth_offset)):
        if value is not None and args.truth is None:
            raise ValueError(f"{option} applies to a --truth file, and none was given")
    if args.truth_origin is not None and args.truth_format != "smartloc":
        raise ValueError("--truth-origin applies to --truth-format smartloc only")
    if args.truth_offset and args.truth_format == "static":
        raise ValueError("--truth-offset changes nothing for --truth-format static, whose one point labels every epoch")


def _solve(args) -> _Solved:
    """Read the inputs, solve and write the output files (a file that cannot be written is noted, not raised)."""
    import estimators
    from . import datasets
    from .features import build_sequence
    from .measurements import load
    from .outputs import (FIGURES, TRUTH_FIGURES, save_figure, solution_figures, write_csv, write_geojson, write_kml,
                          write_pos)
    from .spp import spp

    sample = args.obs is None
    obs_files = [SAMPLE_OBS] if sample else list(args.obs)
    obs = obs_files[0]                                  # names the outputs
    obs_words = " + ".join(map(str, obs_files))
    nav = list(SAMPLE_NAV) if sample else (args.nav or [])
    if not nav:
        missing = next((f for f in obs_files if not Path(f).exists()), None)
        if missing is not None:                     # the missing file first: --nav alone would not make it run
            raise InputError(missing, "cannot read file (No such file or directory)")
        raise InputError(obs, "no navigation file given (--nav)")
    truth_path = SAMPLE_TRUTH if (sample and args.truth is None) else args.truth
    truth_format = "smartloc" if (sample and args.truth is None) else (args.truth_format or "urbannav")
    make_output_folder(args.out)           # before any work: a folder that takes no file costs no solve

    noise, noise_text = _noise(args)
    feature_names = tuple(noise.feature_names) if hasattr(noise, "feature_names") else None
    observations, keep = _read_window(obs_files, args.start, args.end)   # the whole file(s), and the epochs to solve
    spp_config = SppConfig(elevation_mask_deg=args.elevation_mask)
    meas = load(observations if keep.all() else observations.select_epochs(keep), nav,
                systems=tuple(args.systems) if args.systems else None)
    note = unseen_systems_note(noise, meas.systems)
    if note:
        warnings.warn(f"{model_path(args.model or DEFAULT_MODEL)}: {note}")
    fix = spp(meas, spp_config)
    truth, seen = None, []
    if truth_path is not None:
        if truth_format not in datasets.TRUTH_READERS:
            raise InputError(truth_path, f"unknown truth format {truth_format!r}")
        spec = datasets.DatasetSpec("cli", tuple(obs_files), nav, truth_path, truth_format,
                                    time_origin_gps_s=args.truth_origin,
                                    time_offset_s=args.truth_offset or 0.0)
        truth, bad = datasets.align_truth(observations.time_gps_s, spec)   # the whole file's epochs, as always
        truth = truth[keep]
        for line in datasets.truth_note_summary(truth_path, bad):
            print(f"warning: {line}", file=sys.stderr)
        if not np.isfinite(truth).all(axis=1).any():
            hint = " and --truth-origin (GPS seconds of its t = 0)" if truth_format == "smartloc" else ""
            print(f"warning: {truth_path}: no truth epoch matches an epoch of {obs_words}{_window_words(args)}; no "
                  f"accuracy table or error plots (check --truth-format {truth_format}{hint})"
                  f"{datasets.unmatched_time_words(spec, meas.time_gps_s)}", file=sys.stderr)
            truth = None
        else:
            fixed = np.where(fix.ok[:, None], fix.pos_ecef_m, np.nan)
            read_with = spec if args.truth_origin is not None else replace(      # the origin align_truth took: the
                spec, time_origin_gps_s=float(observations.time_gps_s[0]))       # file's first epoch, not --start's
            for note in datasets.truth_fit_notes(read_with, meas.time_gps_s, truth, fixed):
                print(f"warning: {note}", file=sys.stderr)
            seen = seen_epochs_notes(noise, obs_files, meas.time_gps_s, truth)
            if seen:
                name, path = str(args.model or "default"), model_path(args.model or DEFAULT_MODEL)
                named = args.model is None or path == bundled_models().get(name)    # by name, not a path to a copy
                who = f"the bundled model {name!r}" if named else str(path)
                warnings.warn(f"{who}: {'; '.join(seen)}: the accuracy table is in-sample on those epochs")
    from .sequence import DEFAULT_FEATURES

    try:
        seq = build_sequence(meas, fix, feature_names=feature_names or DEFAULT_FEATURES,
                             name=file_names(obs_files),
                             truth_ecef_m=truth, spp_config=spp_config)
    except LfgnssError as err:  # an error about the data that names no file: it is about the observations
        if isinstance(err, (InputError, RinexError)):
            raise
        raise InputError(obs, str(err) + _mask_cause(args.elevation_mask, fix)) from None
    mask_note = _mask_note(noise, args.elevation_mask)      # once the input is known good: an error stays one line
    if mask_note:
        print(f"warning: {mask_note}", file=sys.stderr)
    options = {"noise": noise} if noise is not None else {}
    label = args.backend
    if args.backend == "fgo":
        options["mode"] = args.mode or "batch"
        label += " fixed-lag" if options["mode"] == "fixed-lag" else ""
    if args.smooth:
        options["smooth"] = True
        label += "+rts"
        if args.smooth_lag is not None:
            options["smooth_lag_s"] = args.smooth_lag
            label += f" (lag {args.smooth_lag:g} s)"
    if args.marginals:
        options["covariances"] = True
    if args.formal_sd:
        options["inflate_cov"] = False
    label += " (hand-set noise)" if args.no_model else ""
    label += f" (model {model_tag(Path(args.model))})" if _own_model(args) else ""   # the table names the model
    if args.backend in PROGRESS_BACKENDS:
        options["progress"] = not args.quiet
    estimator = estimators.create(args.backend, **options)
    estimator.name = label
    solution = estimator.solve(seq)

    name = f"{obs_stem(obs)}_{_run_tag(args, options, ''.join(seq.systems))}"
    stem = args.out / name
    # a file that cannot be written (a folder in its place, a full disk) costs that file only: the solution, the
    # other files and the accuracy table are kept, and the run ends with exit code 2
    recorded = replace(solution, backend=solution.backend + _settings_text(args))   # the .pos header's program line
    jobs = [(f"{stem}.pos", lambda p: [write_pos(p, recorded, inputs=[*obs_files, *nav],
                                                 systems="".join(seq.systems))]),
            (f"{stem}.csv", lambda p: [write_csv(p, solution, truth)]),
            (f"{stem}.geojson", lambda p: [write_geojson(p, solution, points=args.points)]),
            (f"{stem}.kml", lambda p: [write_kml(p, solution, points=args.points)])]
    if not args.no_plots:
        figures: dict = {}                  # drawn at the first figure's turn, after the files above are written
        learned = isinstance(getattr(noise, "metadata", None), dict)
        title = f"{seq.name}: {label}" + ("" if _own_model(args) or args.no_model else
                                          f", model {DEFAULT_MODEL.name}" if learned else f", {noise_text}")
        title += "\nin-sample: the model was trained or selected on some of these epochs" if seen else ""

        def save(path: str, name: str) -> list[Path]:
            figures.update(figures or solution_figures(solution, truth, extra_solutions={COARSE_LABEL: _coarse(seq)},
                                                       title=title))
            return [save_figure(path, figures[name])]

        jobs += [(f"{stem}_{name}", lambda p, name=name: save(p, name))
                 for name in (TRUTH_FIGURES if truth is not None else FIGURES)]
    written, failed = [], []
    for path, job in jobs:
        try:
            written += job(path)
        except OSError as err:
            failed.append(f"{err.filename or path}: {cannot_write(err)}")
    return _Solved(obs_words, keep, meas, fix, solution, truth, label, noise_text, written, failed)


def _print_summary(args: argparse.Namespace, solved: _Solved, caught: list[str]) -> None:
    """Warnings on stderr, then the run, its input notes and outputs (unless --quiet) and the accuracy table on stdout.

    The first ``NOTES_SHOWN`` input notes are printed once: on stdout among the run's lines, on stderr with
    --quiet; a caught warning that repeats one (a reader's "first: ..." summary of its notes) is left out.
    """
    from .metrics import accuracy_table, format_text

    notes = list(solved.meas.warnings)
    shown = notes[:NOTES_SHOWN]
    warned = [m for m in dict.fromkeys(caught) if not any(note in m for note in shown)]
    if args.quiet:
        warned = shown + ([f"{solved.obs}: {len(notes)} input notes in all, the first {NOTES_SHOWN} above"]
                          if len(notes) > NOTES_SHOWN else []) + warned
    for message in warned[:10]:
        print(f"warning: {message}", file=sys.stderr)
    if not args.quiet:
        _print_run(solved, shown, len(notes))
    if solved.truth is not None:
        fix, solution, truth = solved.fix, solved.solution, solved.truth
        rows = [accuracy_table(fix.pos_ecef_m, truth, fix.ok, method=COARSE_LABEL),
                accuracy_table(solution.pos_ecef_m, truth, solution.available, method=solved.label)]
        print(format_text(rows))


def solution_words(solution) -> str:
    """One line on what a Solution says of itself: epochs with a position by status, median standard deviations
    east / north / up [m] and satellites used (for a run without truth, the only account of it)."""
    from estimators.base import STATUS_NAMES, STATUS_NONE

    has = solution.has_position()
    status = np.asarray(solution.status)
    counts = ", ".join(f"{name} {int(np.sum(has & (status == code)))}" for code, name in STATUS_NAMES.items()
                       if code != STATUS_NONE and np.any(has & (status == code)))
    words = f"solution: {int(has.sum())} of {has.size} epochs with a position" + (f" ({counts})" if counts else "")
    sd = solution.sd_enu_m()[has]
    if np.isfinite(sd).all(axis=1).any():
        e, n, u = np.nanmedian(sd[np.isfinite(sd).all(axis=1)], axis=0)
        words += f"; median standard deviation east / north / up {e:.2f} / {n:.2f} / {u:.2f} m"
    if has.any():
        words += f"; median {np.median(np.asarray(solution.n_used)[has]):g} satellites used"
    return words


def _print_run(solved: _Solved, shown: list[str], n_notes: int) -> None:
    """The run's lines on stdout: file, systems and back end, coarse fix, input notes and outputs."""
    summary = solved.fix.summary()
    keep = solved.keep
    shown_label = re.sub(r" \((hand-set noise|model [^()]*)\)$", "", solved.label)    # noise_text says it
    of_file = f" of {keep.size} (--start/--end)" if not keep.all() else ""
    print(f"{solved.obs}: {summary['epochs']} epochs{of_file}, systems {''.join(solved.meas.systems)}, backend "
          f"{shown_label} ({solved.noise_text})")
    print(f"coarse fix: {summary['epoch_status']}; observations: {summary['observations']}")
    if n_notes:
        whole = " (the file is read whole: some may be outside --start/--end)" if not keep.all() else ""
        print(f"input notes{whole}: {n_notes} (damaged records or epochs skipped, constellations dropped, stand-ins "
              f"used){f'; the first {NOTES_SHOWN}:' if n_notes > NOTES_SHOWN else ':'}")
    for note in shown:
        print(f"warning: {note}")
    print(solution_words(solved.solution))
    files = [p for p in solved.written if not str(p).endswith(".png")]
    plots = len(solved.written) - len(files)
    print(f"outputs: {', '.join(str(p) for p in files) or 'none'}" + (f" and {plots} plots" if plots else ""))


def _finite_float(text: str) -> float:
    """An option's number, refused by argparse (one line, exit 2) when it is not a finite number."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"needs a finite number, got {text!r}")
    return value


def _gps_time(text: str) -> float:
    """argparse type of --start/--end: GPS seconds [s] from ``WEEK:TOW`` or GPST ``YYYY/MM/DD HH:MM:SS(.s)``."""
    week_tow, calendar = _WEEK_TOW.fullmatch(text), _CALENDAR.fullmatch(text)
    if week_tow and float(week_tow[2]) < SECONDS_PER_WEEK:
        return float(week_tow_to_gps_s(int(week_tow[1]), float(week_tow[2])))
    if week_tow:
        raise argparse.ArgumentTypeError(f"the time of week must be below {SECONDS_PER_WEEK:g} s, got {text!r}")
    if calendar is None:
        raise argparse.ArgumentTypeError(f'needs a GPS time, WEEK:TOW (1900:126700.5) or "YYYY/MM/DD HH:MM:SS" '
                                         f'(2016/06/06 11:11:40.5), got {text!r}')
    seconds = float(calendar[6])
    try:
        stamp = dt.datetime(*(int(v) for v in calendar.groups()[:5]), int(seconds))
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"not a calendar time ({err}), got {text!r}") from None
    return float(datetime64_to_gps_s(np.datetime64(stamp.replace(second=0)))) + seconds


def _systems(text: str) -> str:
    """argparse type of --systems: constellation letters, upper case, each once in the order given (``"g, r"``: GR)."""
    letters = "".join(_SYSTEM_SEPARATORS.split(text)).upper()
    unknown = unknown_systems(letters)
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown constellation letter(s) {unknown!r} in {text!r}; use letters of "
                                         f"{''.join(SYSTEMS)}, e.g. GC, \"G C\" or G,C")
    if not letters:
        raise argparse.ArgumentTypeError(f"needs constellation letters of {''.join(SYSTEMS)}, got {text!r}")
    return "".join(dict.fromkeys(letters))


def _elevation_mask(text: str) -> float:
    """argparse type of --elevation-mask: an elevation in [0, 90) degrees [deg]."""
    value = _finite_float(text)
    if not 0.0 <= value < 90.0:
        raise argparse.ArgumentTypeError(f"needs an elevation in [0, 90) degrees, got {text!r}")
    return value


def _week_tow_text(t: float) -> str:
    """GPS seconds as ``WEEK:TOW`` [s], to the millisecond: ``1900:126700.5``."""
    week, tow = gps_s_to_week_tow(round(t, 3))
    return f"{int(week)}:{_trimmed(f'{tow:.3f}')}"


def _gpst_text(t: float) -> str:
    """GPS seconds [s] in words, to the millisecond: ``2016-06-06 11:11:40.5 GPST (1900:126700.5)``."""
    return f"{_trimmed(gpst_stamp(t))} GPST ({_week_tow_text(t)})"


def _trimmed(number: str) -> str:
    """A decimal's text without trailing zeros after the point: ``40.500`` -> ``40.5``, ``40.000`` -> ``40``."""
    return number.rstrip("0").rstrip(".") if "." in number else number


def _window_text(start: float | None, end: float | None) -> str:
    """--start/--end [GPS s] in words: ``A to B``, ``from A`` or ``up to B``."""
    if start is None:
        return f"up to {_gpst_text(end)}"
    return f"from {_gpst_text(start)}" if end is None else f"{_gpst_text(start)} to {_gpst_text(end)}"


def _window_words(args: argparse.Namespace) -> str:
    """`` in --start/--end`` when the run has a window, else ''."""
    return " in --start/--end" if args.start is not None or args.end is not None else ""


def _read_window(obs_files: list[Path], start: float | None, end: float | None) -> tuple[Observations, np.ndarray]:
    """The whole observation file(s) (several joined in time order: ``datasets.join_observations``) and (T,) bool of
    the epochs in [start, end] [GPS s], inclusive; none: InputError naming the first file."""
    from .datasets import join_observations
    from .rinex import load_obs
    from .sequence import time_span_text

    obs = obs_files[0]
    observations = load_obs(obs) if len(obs_files) == 1 else join_observations([load_obs(f) for f in obs_files])
    t = observations.time_gps_s
    keep = np.ones(t.shape, bool)
    if start is not None:
        keep &= t >= start - WINDOW_TOLERANCE_S
    if end is not None:
        keep &= t <= end + WINDOW_TOLERANCE_S
    if not keep.any() and (start is not None or end is not None):
        files = "the file spans" if len(obs_files) == 1 else \
            f"the files ({file_names(obs_files)}) span, with their gaps,"
        raise InputError(obs, f"no epoch in --start/--end {_window_text(start, end)}; {files} {time_span_text(t)}")
    return observations, keep


def _mask_note(noise, mask_deg: float) -> str | None:
    """Why a learned model may not fit --elevation-mask [deg]: learning.train builds its data with the default mask."""
    if getattr(noise, "metadata", None) is None or mask_deg == DEFAULT_ELEVATION_MASK_DEG:
        return None                                       # hand-set noise, or the mask models are trained with
    return (f"{noise.path}: learned models are trained with a {DEFAULT_ELEVATION_MASK_DEG:g} degree elevation mask, "
            f"this run uses --elevation-mask {mask_deg:g}; its noise estimates may not carry over")


def _mask_cause(mask_deg: float, fix: CoarseFix) -> str:
    """`` (with --elevation-mask 89: ...)`` when a mask [deg] other than the default left no coarse fix, else ''."""
    if mask_deg == DEFAULT_ELEVATION_MASK_DEG or fix.ok.any():
        return ""
    return (f" (with --elevation-mask {mask_deg:g}: too few satellites above {mask_deg:g} degrees for a fix; the "
            f"default is {DEFAULT_ELEVATION_MASK_DEG:g})")


def _settings_text(args: argparse.Namespace) -> str:
    """The window, mask and systems of a run that sets them, as .pos header options: `` --start 1900:126700.5``."""
    text = f" --start {_week_tow_text(args.start)}" if args.start is not None else ""
    text += f" --end {_week_tow_text(args.end)}" if args.end is not None else ""
    mask = args.elevation_mask
    text += f" --elevation-mask {mask:g}" if mask != DEFAULT_ELEVATION_MASK_DEG else ""
    return text + (f" --systems {args.systems}" if args.systems else "")


def _run_tag(args: argparse.Namespace, options: dict, systems: str = "") -> str:
    """What tells this run's output files from another back end's or variant's in the same ``--out``: ``ekf-rts``.

    With --systems, the constellations the run used (``systems``, in GCERJ order): ``--systems CG`` and ``GC`` are one
    run, and ``--systems GC`` on a file of GPS and GLONASS is the ``--systems G`` run (``-sysG``).
    """
    from estimators.ekf import smoothed_name

    tag = smoothed_name(args.backend + ("-fixed-lag" if options.get("mode") == "fixed-lag" else ""), args.smooth,
                        math.inf if args.smooth_lag is None else args.smooth_lag)
    tag += f"-{model_tag(Path(args.model))}" if _own_model(args) else ""
    tag += "-hand-set" if args.no_model else ""
    tag += "-marginals" if args.marginals else ""
    tag += "-formal-sd" if args.formal_sd else ""
    for option, t in (("ts", args.start), ("te", args.end)):          # rnx2rtkp's names; GPS week and time of week [s]
        tag += f"-{option}{_week_tow_text(t).replace(':', '_')}" if t is not None else ""
    tag += f"-mask{args.elevation_mask:g}" if args.elevation_mask != DEFAULT_ELEVATION_MASK_DEG else ""
    return tag + (f"-sys{systems or args.systems}" if args.systems else "")


def obs_stem(obs: str | Path) -> str:
    """The start of a run's output names: the observation file's name without its compression and RINEX suffixes
    (``Berlin_Potsdamer_Platz.obs.gz``: ``Berlin_Potsdamer_Platz``; ``drive.day1.obs`` and ``drive.day2.obs`` keep
    ``day1`` and ``day2``, so their runs in one ``--out`` do not overwrite each other's files)."""
    path = Path(Path(obs).name)
    if path.suffix.lower() in COMPRESSION_SUFFIXES:
        path = Path(path.stem)
    return path.stem or path.name


def _own_model(args: argparse.Namespace) -> bool:
    """Whether the run has a model other than the default one (``--model default`` is the run without --model)."""
    return args.model is not None and model_path(args.model).resolve() != DEFAULT_MODEL.resolve()


def model_tag(path: Path) -> str:
    """A model file's name in output names; a training run's ``model.npz`` goes by its run folder (``runs/a``: ``a``)."""
    if path.stem != "model":
        return path.stem
    return path.parent.resolve().name or path.stem


def _coarse(seq):
    from estimators.base import STATUS_NONE, STATUS_UPDATED, Solution

    ok = np.all(np.isfinite(seq.coarse_ecef_m), axis=1)
    return Solution("least squares", seq.time_gps_s, seq.coarse_ecef_m, np.zeros((len(seq), 3, 3)),
                    seq.coarse_clock_m[:, 0], seq.mask.sum(1), np.where(ok, STATUS_UPDATED, STATUS_NONE))


def main(argv: list[str] | None = None) -> int:
    """Entry point: parse arguments, run, turn input errors into one line on stderr."""
    try:
        args = build_parser().parse_args(argv)      # imports the estimators: half a second to press Ctrl-C in
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    warnings.simplefilter("ignore", FutureWarning)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", UserWarning)
            code = run(args)
        for message in list(dict.fromkeys(str(w.message) for w in caught))[:10]:   # those run did not show
            print(f"warning: {message}", file=sys.stderr)
        return code
    except INPUT_ERRORS as err:
        print(f"error: {one_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # a bug, not bad input: still one line, no traceback, a distinct exit code
        message = " ".join(str(err).split())
        print(f"error: internal error while solving {(args.obs or [SAMPLE_OBS])[0]} ({type(err).__name__}: {message}); "
              f"please report it", file=sys.stderr)
        return 3


if __name__ == "__main__":
    raise SystemExit(main())
