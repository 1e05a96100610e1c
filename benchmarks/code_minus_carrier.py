"""Does code-minus-carrier tell pseudoranges more than 10 m off apart? Areas under the ROC curve against the truth.

    python benchmarks/code_minus_carrier.py            # berlin-pp's train and val splits, print the tables
    python benchmarks/code_minus_carrier.py --write    # ... and write docs/code_minus_carrier.md

A diagnostic, not a method: the observation files' L1 carrier phases (read here with georinex; ``lfgnss.rinex`` keeps
code, C/N0 and Doppler only) are turned into metres (GPS, Galileo and QZSS: the 1575.42 MHz wavelength; GLONASS: its
FDMA wavelength from the navigation files' frequency channel numbers), matched to the sequence's epochs by GPS time to
0.1 s and subtracted from the corrected pseudorange: code minus carrier (CMC). Per satellite arc (broken at a
loss-of-lock flag, a gap over 0.6 s, or 1.5 epoch intervals where that is longer, or a CMC jump over 100 m), CMC less
its lowest value so far in the arc is the "excess", the delay a signal gained since its cleanest moment; less the
arc's lowest value over the whole arc, its
non-causal version; CMC less its running arc mean, the deviation. Each is scored, with minus C/N0, by the area under
the ROC curve for a pseudorange more than 10 m off under the two truth labellings of benchmarks/bad_pseudoranges.py.
The arcs run over the train and validation epochs together (a validation arc may begin in train); the test split is
never read.
"""
from __future__ import annotations

import sys
from pathlib import Path
from collections.abc import Iterable
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from lfgnss.sequence import Sequence

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bad_pseudoranges import (BAD_M, LABELLINGS, SPLIT_WORDS, SPLITS, _concat, _f, roc_auc,  # noqa: E402
                              truth_errors_m)
from page import command_line, nothing, parse, publish, script_parser  # noqa: E402  (sibling modules)

DOC = REPO / "docs" / "code_minus_carrier.md"
DATASETS = ("berlin-pp",)
GAP_S = 0.6                               # an arc breaks where a satellite's usable phases are further apart [s]
GAP_INTERVALS = 1.5                       # ... or further apart than this many epoch intervals, where that is longer
JUMP_M = 100.0                            # ... or where its CMC jumps by more [m]
TIME_KEY_S = 0.1                          # epochs and phases are matched by GPS time to 0.1 s
PHASE_TYPES = ("L1", "L1C")               # RINEX 2 and 3 names of the L1 (C/A) carrier phase
L1_SYSTEMS = ("G", "E", "J", "R")         # constellations with an L1 / E1 phase this script converts
CUES = ("C/N0", "excess", "whole-arc excess", "|deviation from arc mean|")
RMS_AGES_S = (0.0, 20.0)                  # RMS of the error before / after the excess: slots of arcs this old [s]


def glonass_channels(nav_paths: Iterable[str | Path]) -> dict[str, int]:
    """{GLONASS satellite id: its frequency channel number k [-]} from the navigation files (the latest record's)."""
    from lfgnss.navigation import load_nav

    glo = load_nav(list(nav_paths)).glonass
    return {str(sv): int(k) for sv, k in zip(glo.sv, glo.k)}        # sorted by (sv, toe): the last one wins


def l1_wavelengths_m(sv: np.ndarray, channels: dict[str, int]) -> np.ndarray:
    """The L1 carrier wavelength [m] of each satellite id in ``sv`` (any shape); NaN for a constellation without a
    converted L1 phase (BeiDou, SBAS, ...) and for a GLONASS satellite without a channel number in ``channels``."""
    from lfgnss.constants import GLO_L1_BASE_HZ, GLO_L1_STEP_HZ, GPS_L1_HZ, SPEED_OF_LIGHT_M_S

    sv = np.asarray(sv, dtype="<U3")
    ids, where = np.unique(sv, return_inverse=True)                 # a few dozen satellites over many slots
    each = [SPEED_OF_LIGHT_M_S / GPS_L1_HZ if s[:1] in ("G", "E", "J")
            else SPEED_OF_LIGHT_M_S / (GLO_L1_BASE_HZ + GLO_L1_STEP_HZ * channels[s]) if s[:1] == "R" and s in channels
            else np.nan for s in ids]
    return np.array(each, float)[where].reshape(sv.shape)


def read_l1_phases(obs_path: str | Path, systems: tuple[str, ...] = L1_SYSTEMS
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One observation file's L1 phases through georinex: (E,) epoch times [GPS s], (S,) satellite ids, (E, S)
    phases [cycles] (NaN where none) and (E, S) loss-of-lock flags (LLI bit 0). Empty arrays when it has none."""
    import warnings

    import georinex

    from lfgnss.rinex import tags_to_gps_s

    use = {s for s in systems if s in L1_SYSTEMS}
    if not use:                                                     # georinex would read every constellation
        return np.zeros(0), np.zeros(0, "<U3"), np.zeros((0, 0)), np.zeros((0, 0), bool)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ds = georinex.load(obs_path, meas=list(PHASE_TYPES), use=use, useindicators=True)
    name = next((n for n in PHASE_TYPES if n in ds), None)
    if name is None or ds.sizes.get("time", 0) == 0:
        return np.zeros(0), np.zeros(0, "<U3"), np.zeros((0, 0)), np.zeros((0, 0), bool)
    times = tags_to_gps_s(ds.time.values, ds.attrs.get("time_system", "GPS") or "GPS")
    cycles = ds[name].values.astype(float)
    lli = ds[f"{name}lli"].values if f"{name}lli" in ds else np.zeros(cycles.shape)
    slip = (np.nan_to_num(lli).astype(int) & 1).astype(bool)
    return np.asarray(times, float), ds.sv.values.astype("<U3"), cycles, slip


def _time_key(time_gps_s: np.ndarray) -> np.ndarray:
    """Integer keys of GPS times [s] rounded to ``TIME_KEY_S``."""
    return np.round(np.asarray(time_gps_s, float) / TIME_KEY_S).astype(np.int64)


def phases_at_epochs_m(time_gps_s: np.ndarray, sv: np.ndarray, phases: tuple, channels: dict[str, int]
                       ) -> tuple[np.ndarray, np.ndarray]:
    """(T, N) L1 phase [m] and loss-of-lock flag of each slot (satellite ``sv`` (T, N) at epoch ``time_gps_s`` (T,)
    [GPS s]) from ``read_l1_phases``'s tuple, matched by time to 0.1 s; NaN / False where the file has none."""
    p_time, p_sv, cycles, slip = phases
    T, N = np.shape(sv)
    out, flag = np.full((T, N), np.nan), np.zeros((T, N), bool)
    if not np.size(p_time):
        return out, flag
    keys = _time_key(p_time)
    order = np.argsort(keys, kind="stable")
    row = np.searchsorted(keys[order], _time_key(time_gps_s))
    row_ok = row < keys.size
    row = order[np.minimum(row, keys.size - 1)]
    row_ok &= keys[row] == _time_key(time_gps_s)
    ids, where = np.unique(np.asarray(sv, dtype="<U3"), return_inverse=True)
    col_of = {s: j for j, s in enumerate(p_sv)}
    col = np.array([col_of.get(s, -1) for s in ids], int)[where].reshape(T, N)
    ok = row_ok[:, None] & (col >= 0)
    r, c = np.broadcast_to(row[:, None], (T, N))[ok], col[ok]
    out[ok] = cycles[r, c] * l1_wavelengths_m(np.asarray(sv)[ok], channels)
    flag[ok] = slip[r, c]
    return out, flag


def arc_gap_s(time_s: np.ndarray) -> float:
    """The gap [s] that breaks an arc: ``GAP_S``, or ``GAP_INTERVALS`` median epoch intervals of ``time_s`` [s] where
    that is longer (at 1 Hz every epoch is 1 s after the last, which a 0.6 s gap would break every time)."""
    steps = np.diff(np.asarray(time_s, float))
    return max(GAP_S, GAP_INTERVALS * float(np.median(steps))) if steps.size else GAP_S


def arc_cues(time_s: np.ndarray, sv: np.ndarray, usable: np.ndarray, cmc_m: np.ndarray, slip: np.ndarray,
             gap_s: float = GAP_S, jump_m: float = JUMP_M) -> dict[str, np.ndarray]:
    """Per satellite arc over the ``usable`` slots (T, N) (times ``time_s`` (T,) [s], ids ``sv`` (T, N)): an arc
    breaks at a loss-of-lock flag ``slip``, a gap over ``gap_s`` [s] or a CMC jump over ``jump_m`` [m]. Returns (T, N)
    arrays, NaN (arc -1) off the usable slots: "arc" id, "age" [s] since the arc began, "excess" [m] (CMC less its
    lowest value so far in the arc), "whole-arc excess" [m] (less the arc's lowest value) and "deviation" [m] (CMC
    less its running arc mean, the current epoch included)."""
    import pandas as pd

    time_s, sv, usable = np.asarray(time_s, float), np.asarray(sv), np.asarray(usable, bool) & np.isfinite(cmc_m)
    T, N = usable.shape
    flat = np.flatnonzero(usable.ravel())
    t, ids, c, s = time_s[flat // N], sv.ravel()[flat], np.asarray(cmc_m, float).ravel()[flat], \
        np.asarray(slip, bool).ravel()[flat]
    order = np.lexsort((t, ids))                                   # by satellite, then time
    flat, t, ids, c, s = flat[order], t[order], ids[order], c[order], s[order]
    new = np.ones(flat.size, bool)
    new[1:] = (ids[1:] != ids[:-1]) | s[1:] | (np.diff(t) > gap_s) | (np.abs(np.diff(c)) > jump_m)
    arc = np.cumsum(new) - 1
    g = pd.Series(c).groupby(arc)
    running_mean = g.cumsum().to_numpy() / (g.cumcount().to_numpy() + 1)
    values = {"arc": arc.astype(float), "age": t - pd.Series(t).groupby(arc).transform("first").to_numpy(),
              "excess": c - g.cummin().to_numpy(), "whole-arc excess": c - g.transform("min").to_numpy(),
              "deviation": c - running_mean}
    out = {}
    for key, v in values.items():
        full = np.full(T * N, -1.0 if key == "arc" else np.nan)
        full[flat] = v
        out[key] = full.reshape(T, N)
    out["arc"] = out["arc"].astype(int)
    return out


def _arrays(piece: "Sequence") -> dict[str, np.ndarray]:
    """A piece's epochs as the arrays read here (time, ids, mask, pseudorange, C/N0, each labelling's error)."""
    return {"time": piece.time_gps_s, "sv": piece.sv, "mask": piece.mask, "pr": piece.pr_m, "cn0": piece.cn0_dbhz,
            **{f"error {k}": e for k, e in truth_errors_m(piece).items()}}


def dataset_signals(dataset_id: str, splits: tuple[str, ...] = SPLITS) -> dict[str, dict[str, np.ndarray]] | None:
    """{split: flat arrays over its labelled usable slots with an L1 phase: each labelling's error [m], "age" [s],
    "cue ..." (higher = worse), "excess" and "whole-arc excess" [m]; "usable": (1,) the split's usable slot count},
    the arcs built over the train and validation epochs together; None, with a one-line note on stderr, when the
    observation files hold no L1 phase."""
    from lfgnss import datasets

    spec = datasets.get(dataset_id)
    phases = [read_l1_phases(p, spec.systems or L1_SYSTEMS) for p in spec.obs]
    phases = [ph for ph in phases if ph[0].size and np.isfinite(ph[2]).any()]
    if not phases:
        print(f"{dataset_id}: skipped, no L1 carrier phase in {', '.join(p.name for p in spec.obs)}", file=sys.stderr)
        return None
    channels = glonass_channels(spec.nav) if any(s[:1] == "R" for ph in phases for s in ph[1]) else {}
    pieces = {split: datasets.load_split(dataset_id, split) for split in SPLITS}
    seq = _concat([_arrays(p) for split in SPLITS for p in pieces[split]])
    unknown = sorted({s for s in seq["sv"][seq["mask"]] if s[:1] == "R" and s not in channels})
    if unknown:
        print(f"{dataset_id}: {', '.join(unknown)} without a frequency channel in the navigation files: their phases "
              "are left out", file=sys.stderr)
    phase_m, slip = np.full(seq["mask"].shape, np.nan), np.zeros(seq["mask"].shape, bool)
    for ph in phases:                                               # several files: each fills the epochs it has
        m, f = phases_at_epochs_m(seq["time"], seq["sv"], ph, channels)
        fill = np.isnan(phase_m) & np.isfinite(m)
        phase_m[fill], slip[fill] = m[fill], f[fill]
    cues = arc_cues(seq["time"], seq["sv"], seq["mask"], seq["pr"] - phase_m, slip, arc_gap_s(seq["time"]))
    out = {}
    for split in splits:
        times = np.concatenate([p.time_gps_s for p in pieces[split]] or [np.zeros(0)])
        usable = seq["mask"] & np.isin(_time_key(seq["time"]), _time_key(times))[:, None]
        on = usable & np.isfinite(cues["excess"])                 # a phase, and a finite pseudorange
        if not on.any():
            print(f"{dataset_id}: no labelled epoch with phases in its {split} split: left out", file=sys.stderr)
            continue
        out[split] = {**{f"error {k}": seq[f"error {k}"][on] for k in LABELLINGS},
                      "age": cues["age"][on], "arc": cues["arc"][on], "excess": cues["excess"][on],
                      "whole-arc excess": cues["whole-arc excess"][on],
                      "cue C/N0": -seq["cn0"][on], "cue excess": cues["excess"][on],
                      "cue whole-arc excess": cues["whole-arc excess"][on],
                      "cue |deviation from arc mean|": np.abs(cues["deviation"][on]),
                      "usable": np.array([int(usable.sum())])}
    return out


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x ** 2))) if x.size else float("nan")


def summary(sig: dict[str, np.ndarray], labelling: str) -> dict:
    """One row: labelled count (of the usable slots), bad count and share, arcs, median arc age [s], each cue's area
    under the ROC curve, corr(error, excess), and per ``RMS_AGES_S`` the RMS error [m] before and after subtracting
    the excess and the whole-arc excess."""
    error = sig[f"error {labelling}"]
    on = np.isfinite(error)
    bad = np.abs(np.nan_to_num(error)) > BAD_M
    nan = float("nan")
    row = {"usable": int(sig["usable"].sum()), "labelled": int(on.sum()), "n_bad": int(bad[on].sum()),
           "bad": float(bad[on].mean()) if on.any() else nan, "arcs": int(np.unique(sig["arc"][on]).size),
           "age_s": float(np.median(sig["age"][on])) if on.any() else nan,
           "auc": {c: roc_auc(sig[f"cue {c}"][on], bad[on]) for c in CUES},
           "corr": float(np.corrcoef(error[on], sig["excess"][on])[0, 1]) if on.sum() > 1 else nan, "rms": {}}
    for age in RMS_AGES_S:
        m = on & (sig["age"] >= age)
        row["rms"][age] = {"n": int(m.sum()), "before": _rms(error[m]), "excess": _rms(error[m] - sig["excess"][m]),
                           "whole": _rms(error[m] - sig["whole-arc excess"][m])}
    return row


def run(dataset_ids: list[str], splits: tuple[str, ...] = SPLITS) -> list[dict]:
    """Rows (dataset, split, labelling, ``summary``) for each dataset with its files and L1 phases, the splits pooled
    as a last row per dataset and labelling when there are several. ValueError for the test split."""
    from lfgnss import datasets

    if "test" in splits:
        raise ValueError("code_minus_carrier: the test split is not read by this diagnostic")
    rows = []
    for dataset_id in datasets.present(list(dataset_ids), report=lambda line: print(line, file=sys.stderr)):
        per_split = dataset_signals(dataset_id, splits)
        if not per_split:
            continue
        if len(per_split) > 1:
            per_split["+".join(per_split)] = _concat(list(per_split.values()))
        for split, sig in per_split.items():
            for labelling in LABELLINGS:
                rows.append({"dataset": dataset_id, "split": split, "labelling": labelling, **summary(sig, labelling)})
    return rows


def _split_words(split: str) -> str:
    return " + ".join(SPLIT_WORDS.get(s, s) for s in split.split("+"))


def tables(rows: list[dict], labelling: str) -> list[str]:
    """Markdown lines: the labelling's areas table and its RMS table."""
    mine = [r for r in rows if r["labelling"] == labelling]
    head = " | ".join(c.replace("|", "\\|") for c in CUES)
    out = [f"| dataset / split | labelled (of usable) | bad | arcs | median arc age [s] | {head} | "
           "corr(error, excess) |", "| --- |" + " ---: |" * (len(CUES) + 5)]
    for r in mine:
        out.append(f"| {r['dataset']} {_split_words(r['split'])} | {r['labelled']} ({r['usable']}) | {r['n_bad']} "
                   f"({_f(100 * r['bad'], '.0f')} %) | {r['arcs']} | {_f(r['age_s'], '.1f')} | "
                   + " | ".join(_f(r["auc"][c]) for c in CUES) + f" | {_f(r['corr'], '.2f')} |")
    out += ["", "RMS of the error [m], as it is and less the excess (causal / whole arc):", "",
            "| dataset / split | " + " | ".join(f"arc age >= {a:g} s: signals | RMS | - excess | - whole-arc excess"
                                                 for a in RMS_AGES_S) + " |",
            "| --- |" + " ---: |" * (4 * len(RMS_AGES_S))]
    for r in mine:
        out.append(f"| {r['dataset']} {_split_words(r['split'])} | " + " | ".join(
            f"{q['n']} | {_f(q['before'], '.1f')} | {_f(q['excess'], '.1f')} | {_f(q['whole'], '.1f')}"
            for q in r["rms"].values()) + " |")
    return out + [""]


def markdown(rows: list[dict], command: str) -> str:
    """The page: a header paragraph, the physics reading, and per labelling the two tables of ``tables``."""
    from learning.loss import STRONGEST_MIN_SATS

    out = ["# Code minus carrier against bad pseudoranges", "",
           f"Produced by `{command}` (area under the ROC curve for a pseudorange more than {BAD_M:g} m off, bad "
           "against good: rank statistic, ties counted half, 0.5 is chance, 1 ranks every bad signal as worse). It "
           "reads the truth: a diagnostic, nothing is chosen from it, and only the train and validation splits are "
           "read (train + validation: the two pooled). Labelled as in "
           "[bad_pseudoranges.md](bad_pseudoranges.md): each usable pseudorange of an epoch with truth that has an "
           "L1 carrier phase, its error at the true position less a receiver clock per epoch and constellation "
           "(*median*: the constellation's epoch median; *strongest 3*: the median of its three highest-C/N0 "
           f"signals' errors, C/N0 ties broken by slot order, where the constellation has {STRONGEST_MIN_SATS} "
           "satellites or more). Code minus carrier (CMC): the corrected pseudorange less the L1 phase in metres "
           "(read with georinex; GPS / Galileo / QZSS wavelength at 1575.42 MHz, GLONASS at 1602 + 0.5625 k MHz, k "
           "from the navigation files; matched to the epochs by GPS time to 0.1 s). Per satellite arc, over the "
           f"train and validation epochs together (an arc breaks at a loss-of-lock flag, a gap over {GAP_S:g} s, or "
           f"{GAP_INTERVALS:g} epoch intervals where that is longer, or a "
           f"CMC jump over {JUMP_M:g} m): *excess*, CMC less its lowest value so far in the arc, the delay the "
           "signal gained since its cleanest moment (causal); *whole-arc excess*, less the arc's lowest value "
           "(non-causal); *|deviation from arc mean|*, |CMC less its running arc mean|; and minus C/N0. Arc age: "
           "seconds since the arc's first epoch; an arc crossing the train / validation boundary counts in both "
           "splits' rows and once in the pooled one. Labelled (of usable): the labelled slots with a phase, of the "
           "split's usable slots.", "",
           "Reading: a signal received only by reflection (NLOS) has its carrier delayed by the same extra path as "
           "its code, so its code minus carrier stays flat while the pseudorange is tens of metres long; CMC moves "
           "only with multipath interference (a direct signal plus reflections, which pull code and carrier apart "
           "differently), with ionospheric divergence and with noise. So where the excess scores near chance and the "
           "deviation below it (bad signals steadier than good ones), the large errors are mostly of the first "
           "kind, and subtracting the excess can take off only the part that interference adds.", ""]
    for labelling, words in LABELLINGS.items():
        out += [f"## Clock: {labelling} ({words})", ""] + tables(rows, labelling)
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    """Run, print, and with ``--write`` write the Markdown page."""
    p = script_parser(__doc__, f"write {DOC.relative_to(REPO)}", DATASETS, SPLITS)
    args = parse(p, argv, "code_minus_carrier.py")
    if args is None:
        return 2
    rows = run(args.datasets, tuple(args.splits))
    if not rows:
        return nothing("code_minus_carrier.py", "no dataset with its files and L1 phases: nothing to score")
    return publish(markdown(rows, command_line("code_minus_carrier.py", argv)), DOC, args.write)


if __name__ == "__main__":
    raise SystemExit(main())
