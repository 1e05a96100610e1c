"""Whole ``python -m lfgnss.solve`` wall time as a ratio to RTKLIB ``rnx2rtkp`` (issue 6).

    python benchmarks/solve_speed.py                        # every available dataset, 3 repeats, print the tables
    python benchmarks/solve_speed.py --repeat 3 --write     # ... and write docs/solve_speed.md
    python benchmarks/solve_speed.py --datasets hk-tst-2019 --backends ekf --no-stages
    git archive HEAD | tar -x -C /tmp/head && python benchmarks/solve_speed.py --code /tmp/head   # time a commit

For each dataset, in the same run and interleaved repeat by repeat:

* ``rnx2rtkp`` on the whole observation file with the benchmark settings (``lfgnss.rtklib``);
* ``python -m lfgnss.solve --backend B`` on the same whole files and constellations, as a subprocess (interpreter
  start, imports, reading, coarse fix, features, the bundled model, the estimator and writing the outputs all
  count), once with an empty ``LFGNSS_CACHE`` (cold: the RINEX files are parsed) and once more with the cache that
  run left (warm: parsed observations and navigation are read back);
* unless ``--no-stages``, the same steps in-process in a fresh interpreter, each timed alone.

Each figure is the median over ``--repeat`` repeats. Ratios are ours / RTKLIB.
"""
from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import resource
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BENCH_DIR = Path(__file__).resolve().parent
DOC = REPO / "docs" / "solve_speed.md"
#: The tree whose lfgnss, estimators and learning are timed (``--code``; default this checkout).
CODE = REPO
DATASETS = ("hk-tst-2019", "berlin-pp", "hk-tst-static-2020")
BACKENDS = ("ekf", "fgo")
# The stage child imports this module by name, so the module itself imports only the standard library at the top:
# lfgnss, numpy and the estimators are imported inside the functions, and their import time is a stage of its own.


def _env(cache: Path) -> dict[str, str]:
    """The environment of a timed child: this one with ``LFGNSS_CACHE`` set and the repository importable."""
    path = os.pathsep.join(p for p in (str(CODE), os.environ.get("PYTHONPATH", "")) if p)
    env = {**os.environ, "LFGNSS_CACHE": str(cache), "PYTHONPATH": path}
    env.pop("PYTHONDONTWRITEBYTECODE", None)   # else every timed run compiles the package again (0.13-0.17 s), as
    return env                                 # an installed package never does; the warm-up run writes the .pyc


def _child_cpu() -> float:
    """User + system CPU seconds of every finished child process so far."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _timed_process(cmd: list[str], env: dict[str, str]) -> tuple[float, float, str]:
    """(wall seconds, CPU seconds, stdout) of a subprocess; RuntimeError with its stderr tail if it fails."""
    c0, t0 = _child_cpu(), time.perf_counter()
    proc = subprocess.run(cmd, env=env, cwd=CODE, capture_output=True, text=True)
    seconds, cpu = time.perf_counter() - t0, _child_cpu() - c0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited with {proc.returncode}: {proc.stderr.strip()[-2000:]}")
    return seconds, cpu, proc.stdout


def solve_command(spec, backend: str, out: Path) -> list[str]:
    """``python -m lfgnss.solve`` on the dataset's whole files and constellations, default (bundled) model."""
    cmd = [sys.executable, "-m", "lfgnss.solve", "--backend", backend, "--obs", str(spec.obs[0]),
           "--nav", *map(str, spec.nav), "--out", str(out), "--no-plots"]
    return cmd + (["--systems", "".join(spec.systems)] if spec.systems else [])


def time_rtklib(spec, workdir: Path) -> tuple[float, float]:
    """(wall, CPU) seconds of ``rnx2rtkp`` on the whole observation file with the benchmark settings."""
    from lfgnss.rtklib import run_rnx2rtkp

    c0 = _child_cpu()
    _, seconds = run_rnx2rtkp(spec.obs[0], spec.nav, workdir / f"{spec.id}.pos", systems=spec.systems)
    return seconds, _child_cpu() - c0


def time_solve(spec, backend: str, workdir: Path) -> dict[str, tuple[float, float]]:
    """(wall, CPU) seconds of the solve command, ``cold`` with an empty cache, then ``warm`` with the one it left."""
    cache = Path(tempfile.mkdtemp(prefix=f"cache-{backend}-", dir=workdir))
    cmd = solve_command(spec, backend, workdir / f"out-{backend}")
    return {state: _timed_process(cmd, _env(cache))[:2] for state in ("cold", "warm")}


def stage_times(obs: str, nav: list[str], systems: str | None, backends: list[str]) -> dict[str, float]:
    """In-process seconds of each step of ``lfgnss.solve.run``, imports first (run in a fresh interpreter)."""
    t0 = time.perf_counter()
    import warnings

    import estimators
    from estimators.noise import FixedNoise
    from lfgnss import solve
    from lfgnss.features import build_sequence
    from lfgnss.measurements import load
    from lfgnss.navigation import load_nav
    from lfgnss.outputs import write_csv, write_geojson, write_kml, write_pos
    from lfgnss.rinex import load_obs
    from lfgnss.sequence import DEFAULT_FEATURES
    from lfgnss.spp import spp

    warnings.simplefilter("ignore")
    t = {"imports": time.perf_counter() - t0}

    def lap(label: str, fn, *a, **k):
        start = time.perf_counter()
        out = fn(*a, **k)
        t[label] = time.perf_counter() - start
        return out

    observations = lap("read obs", load_obs, obs)
    navigation = lap("read nav", load_nav, nav)
    meas = lap("sat states + QC", load, observations, navigation, systems=tuple(systems) if systems else None)
    fix = lap("spp", spp, meas)
    args = solve.build_parser().parse_args(["--obs", obs, "--nav", *nav])
    noise, _ = lap("model load", solve._noise, args)
    names = tuple(noise.feature_names) if hasattr(noise, "feature_names") else DEFAULT_FEATURES
    seq = lap("features", build_sequence, meas, fix, feature_names=names, name=Path(obs).name)
    r, vc = lap("noise forward", noise, seq)
    with tempfile.TemporaryDirectory(prefix="lfgnss-stages-") as out:
        for backend in backends:
            options = {"mode": "batch"} if backend == "fgo" else {}
            sol = lap(f"{backend} estimator", estimators.create(backend, noise=FixedNoise(r, vc), **options).solve, seq)
            stem = f"{out}/{backend}"
            lap(f"{backend} write", lambda: [write_pos(f"{stem}.pos", sol), write_csv(f"{stem}.csv", sol, None),
                                             write_geojson(f"{stem}.geojson", sol), write_kml(f"{stem}.kml", sol)])
    return t


def time_stages(spec, backends: list[str], cache: Path) -> dict[str, float]:
    """:func:`stage_times` in a fresh interpreter with ``LFGNSS_CACHE=cache``."""
    call = (f"import json,sys; sys.path.insert(0, {str(BENCH_DIR)!r}); import solve_speed as s; "
            f"print(json.dumps(s.stage_times({str(spec.obs[0])!r}, {[str(n) for n in spec.nav]!r}, "
            f"{''.join(spec.systems) if spec.systems else None!r}, {list(backends)!r})))")
    out = _timed_process([sys.executable, "-c", call], _env(cache))[2]
    return json.loads(out.strip().splitlines()[-1])


def median_dicts(runs: list[dict[str, float]]) -> dict[str, float]:
    """Key-wise median of dicts with the same keys."""
    return {k: statistics.median(r[k] for r in runs) for k in runs[0]}


def measure(spec, backends: list[str], repeat: int, stages: bool, workdir: Path) -> dict:
    """Median seconds of rnx2rtkp, each backend cold and warm, and (optionally) the in-process stages."""
    from lfgnss.rinex import load_obs

    runs, cpus, cold_stages, warm_stages = [], [], [], []
    for k in range(repeat):
        timings = {"rnx2rtkp": time_rtklib(spec, workdir)}
        for backend in backends:
            timings.update({f"{backend} {state}": t for state, t in time_solve(spec, backend, workdir).items()})
        runs.append({name: wall for name, (wall, _) in timings.items()})
        cpus.append({name: cpu for name, (_, cpu) in timings.items()})
        if stages:
            cache = Path(tempfile.mkdtemp(prefix="cache-stages-", dir=workdir))
            cold_stages.append(time_stages(spec, backends, cache))
            warm_stages.append(time_stages(spec, backends, cache))
        print(f"  {spec.id} repeat {k + 1}/{repeat}: " + ", ".join(f"{n} {w:.2f} s (CPU {c:.2f} s)"
                                                                    for n, (w, c) in timings.items()),
              file=sys.stderr, flush=True)
    result = {"dataset": spec.id, "epochs": len(load_obs(spec.obs[0], cache=False)), "wall": median_dicts(runs),
              "cpu": median_dicts(cpus)}
    if stages:
        result["stages"] = {"cold": median_dicts(cold_stages), "warm": median_dicts(warm_stages)}
    return result


def warm_up(specs: list, backends: list[str], workdir: Path) -> None:
    """One untimed solve per dataset and backend, so bytecode compilation and cold OS file caches do not count."""
    for spec in specs:
        for backend in backends:
            time_solve(spec, backend, workdir)


def baseline(repeat: int, workdir: Path) -> dict[str, float]:
    """Median seconds of a bare interpreter and of ``python -m lfgnss.solve --help`` (start + CLI imports)."""
    env = _env(Path(tempfile.mkdtemp(prefix="cache-base-", dir=workdir)))
    bare = [_timed_process([sys.executable, "-c", "pass"], env)[0] for _ in range(repeat)]
    helps = [_timed_process([sys.executable, "-m", "lfgnss.solve", "--help"], env)[0] for _ in range(repeat)]
    return {"python -c pass": statistics.median(bare), "lfgnss.solve --help": statistics.median(helps)}


def loadavg() -> str:
    """The 1, 5 and 15 minute load averages, or '-' where the OS has none."""
    return ", ".join(f"{x:.2f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "-"


def machine_info() -> str:
    """One line: CPU count and model, Python, numpy, OS and the rnx2rtkp used."""
    import numpy as np

    from lfgnss.rtklib import rnx2rtkp_path

    cpu = platform.processor() or platform.machine()
    try:
        names = [ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                 if ln.startswith("model name")]
        cpu = names[0] if names else cpu
    except OSError:
        pass
    return (f"{os.cpu_count()} CPUs ({cpu}); Python {platform.python_version()}, "
            f"numpy {np.__version__}, {platform.system()} {platform.release()}; rnx2rtkp {rnx2rtkp_path()}")


def code_version() -> str:
    """Which code was timed: the commit of a git checkout (working-tree changes not checked), else the folder."""
    try:
        head = subprocess.run(["git", "-C", str(CODE), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        head = ""
    if head and (CODE / ".git").exists():
        return f"the checkout {CODE} at commit {head} (plus any uncommitted changes)"
    return f"the tree {CODE}"


def _row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def speed_table(results: list[dict], backends: list[str], clock: str = "wall") -> str:
    """Markdown table: ``clock`` (wall or cpu) seconds and ratios to rnx2rtkp per dataset."""
    head = ["dataset", "epochs", "rnx2rtkp [s]"]
    for b in backends:
        head += [f"solve {b} cold [s] (ratio)", f"solve {b} warm [s] (ratio)"]
    lines = [_row(head), "|" + "---|" * len(head)]
    for result in results:
        r = result[clock]
        cells = [result["dataset"], str(result["epochs"]), f"{r['rnx2rtkp']:.2f}"]
        for b in backends:
            cells += [f"{r[f'{b} {c}']:.2f} ({r[f'{b} {c}'] / r['rnx2rtkp']:.1f}x)" for c in ("cold", "warm")]
        lines.append(_row(cells))
    return "\n".join(lines) + "\n"


def _backend_sum(stages: dict[str, float], backend: str, backends: list[str]) -> float:
    """Seconds of the shared steps plus the steps of ``backend`` (what one solve run does in-process)."""
    others = tuple(f"{b} " for b in backends if b != backend)
    return sum(v for k, v in stages.items() if not k.startswith(others))


def stages_table(results: list[dict], backends: list[str]) -> str:
    """Markdown table: in-process seconds per step, cold and warm cache, per dataset."""
    rows = [r for r in results if "stages" in r]
    if not rows:
        return ""
    keys = list(rows[0]["stages"]["cold"])
    head = ["step"] + [f"{r['dataset']} {c}" for r in rows for c in ("cold", "warm")]
    lines = [_row(head), "|" + "---|" * len(head)]
    for key in keys:
        lines.append(_row([key] + [f"{r['stages'][c][key]:.3f}" for r in rows for c in ("cold", "warm")]))
    for b in backends:
        lines.append(_row([f"**sum for {b}**"] + [f"{_backend_sum(r['stages'][c], b, backends):.2f}"
                                                  for r in rows for c in ("cold", "warm")]))
    return "\n".join(lines) + "\n"


def report(results: list[dict], backends: list[str], base: dict[str, float], info: str, load_start: str,
           repeat: int) -> str:
    """The tables and the fixed costs, as Markdown."""
    text = "Wall time [s] (ratio ours / rnx2rtkp):\n\n" + speed_table(results, backends)
    text += ("\nCPU time [s], user + system of the process and its children (ratio ours / rnx2rtkp); less "
             "sensitive than wall time to other load on the machine, but it counts every thread numpy or gtsam "
             "runs in parallel:\n\n" + speed_table(results, backends, "cpu"))
    text += (f"\nFixed costs (median of {repeat}): bare `python -c pass` {base['python -c pass']:.2f} s; "
             f"`python -m lfgnss.solve --help` (interpreter + the CLI's imports: lfgnss and estimators; filterpy with "
             f"scipy, gtsam and pandas load only when used) {base['lfgnss.solve --help']:.2f} s.\n")
    stages = stages_table(results, backends)
    if stages:
        text += ("\nIn-process steps of `lfgnss.solve.run` [s], each timed alone in a fresh interpreter (median of "
                 f"{repeat}); `cold` = empty cache, `warm` = the cache the cold run left. `imports`: every module "
                 "`solve.run` imports (lfgnss, estimators; filterpy and scipy come with the ekf estimator, gtsam "
                 "with the fgo one); `read obs` "
                 "/ `read nav`: `load_obs` / `load_nav` (parse and write the cache, or read it back; parsing imports "
                 "pandas); `sat states + QC`: `load` on "
                 "the parsed objects; `spp`: the least-squares coarse fix; `model load`: `solve._noise` (the bundled "
                 "model file); `features`: `build_sequence`; `noise forward`: the model's numpy forward pass over "
                 "all epochs (inside the estimator in `solve`); `B estimator`: `estimators.create(B).solve` given "
                 "that noise; `B write`: .pos, .csv, .geojson, .kml. The sums leave out interpreter start and exit."
                 "\n\n" + stages)
    return text + (f"\nMachine: {info}. Load average (1, 5, 15 min) {load_start} at the start, {loadavg()} at the "
                   f"end.\n\nCode: {code_version()}.\n")


def write_doc(text: str, command: str, repeat: int) -> None:
    """docs/solve_speed.md: the command, the date, what is counted, the tables."""
    DOC.parent.mkdir(parents=True, exist_ok=True)
    DOC.write_text(f"""# Whole `solve` wall time vs RTKLIB `rnx2rtkp`

Generated by `{command}` on {dt.datetime.now().astimezone():%Y-%m-%d %H:%M %Z} (edit the script, not this file).

What is counted, per dataset, in the same run (repeats interleaved; each figure the median of {repeat}):

* **rnx2rtkp**: wall time of the `rnx2rtkp` process on the whole observation file with the benchmark settings
  (`lfgnss.rtklib.run_rnx2rtkp`: single point, L1, 10 deg mask, broadcast ionosphere, Saastamoinen, the dataset's
  constellations), writing its `.pos` file.
* **solve B**: wall time of the whole `python -m lfgnss.solve --backend B --obs OBS --nav NAV... --systems SYS
  --out DIR --no-plots` subprocess on the same files and constellations, as a user runs it: interpreter start,
  imports (numpy; filterpy with scipy only for ekf, gtsam only for fgo; pandas only to parse RINEX,
  georinex/xarray only to parse navigation files), RINEX
  reading, satellite states and QC, the least-squares coarse fix, features, the bundled model
  (`lfgnss/data/model/lfgnss-default.npz`, loaded and run with numpy), the estimator (`fgo` in batch mode), and
  writing `.pos`, `.csv`, `.geojson` and `.kml`. No truth is given, so no accuracy table and no plots.
  **cold**: `LFGNSS_CACHE` points to a new empty folder, so both RINEX files are parsed; **warm**: the same
  command again, reading the parsed observations and navigation back from the cache that the cold run wrote.
  One untimed solve per dataset and back end runs first, so compiling the bytecode and reading the files into
  the OS cache the very first time do not count.
* Ratio = ours / rnx2rtkp (lower is better; 1.0x = as fast as RTKLIB).

Timings are wall-clock on a shared machine and move by tens of % between runs.

{text}""")
    print(f"wrote {DOC}", file=sys.stderr)


def available(ids: list[str]) -> list:
    """Specs of the datasets whose files exist; a message for each skipped one."""
    from lfgnss import datasets

    specs = []
    for dataset_id in ids:
        spec = datasets.get(dataset_id)
        missing = spec.missing()
        if missing:
            print(f"{dataset_id}: skipped, missing {missing[0]}", file=sys.stderr)
        else:
            specs.append(spec)
    return specs


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, measure, print the Markdown, optionally write docs/solve_speed.md."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0].replace("``", ""))  # no reST quotes
    parser.add_argument("--datasets", nargs="+", default=list(DATASETS),
                        help=f"dataset ids (default: {' '.join(DATASETS)})")
    parser.add_argument("--backends", nargs="+", default=list(BACKENDS), choices=BACKENDS,
                        help=f"solve back ends (default: {' '.join(BACKENDS)})")
    parser.add_argument("--repeat", type=int, default=3, help="repeats per measurement, the median is reported "
                                                              "(default: 3)")
    parser.add_argument("--no-stages", dest="stages", action="store_false", help="skip the in-process step times")
    parser.add_argument("--write", action="store_true", help=f"write {DOC.relative_to(REPO)}")
    parser.add_argument("--code", type=Path, default=REPO,
                        help="time the lfgnss/estimators/learning of this tree, e.g. a commit exported with "
                             "`git archive` (default: this checkout); the datasets stay those of this checkout")
    args = parser.parse_args(argv)
    if args.repeat < 1:
        parser.error("--repeat must be at least 1")
    if not (args.code / "lfgnss" / "solve.py").is_file():
        parser.error(f"--code {args.code}: no lfgnss/solve.py there")
    global CODE
    CODE = args.code.resolve()
    os.environ.setdefault("LFGNSS_SHARED_DATA", str(REPO.parent / "shared" / "data"))
    sys.path.insert(0, str(CODE))
    from lfgnss.rtklib import rtklib_available

    if not rtklib_available():
        print("rnx2rtkp not found (Debian package 'rtklib'); nothing to compare against", file=sys.stderr)
        return 2
    specs = available(args.datasets)
    if not specs:
        return 2
    info, load_start = machine_info(), loadavg()
    with tempfile.TemporaryDirectory(prefix="lfgnss-solve-speed-") as tmp:
        print("warm-up: one untimed solve per dataset and backend", file=sys.stderr, flush=True)
        warm_up(specs, args.backends, Path(tmp))
        base = baseline(args.repeat, Path(tmp))
        results = []
        for spec in specs:
            print(f"{spec.id}: {args.repeat} repeat(s)", file=sys.stderr, flush=True)
            results.append(measure(spec, args.backends, args.repeat, args.stages, Path(tmp)))
    text = report(results, args.backends, base, info, load_start, args.repeat)
    print(text)
    if args.write:
        command = shlex.join(["python", "benchmarks/solve_speed.py", *(argv if argv is not None else sys.argv[1:])])
        write_doc(text, command.strip(), args.repeat)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
