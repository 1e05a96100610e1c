"""Training speed of a recipe on each device, thread count and batch size (a benchmark script, not a test).

    python benchmarks/train_speed.py --config learning/configs/shipped.toml --device cpu --device cuda
                                     [--threads 1 --threads 16] [--batch-size 16 --batch-size 64] [--epochs 3]
                                     [--out speed.md]

The data are prepared once (``learning.train.prepare``, never the test split); then each setting trains the
recipe from the same seed for ``--epochs`` epochs in a scratch folder, exactly as ``learning.train`` does
(training steps, validation, checkpoints). An epoch's time is the median over the epochs after the first (the
first pays for CUDA start-up and kernel caching). ``speed-up`` is against the first setting of the table.
Settings of one batch size start from the same weights and see the same windows in the same order, so their
validation RMSE after the last epoch should agree to rounding; ``max |dRMSE|`` says how far they do.
"""
from __future__ import annotations

import argparse
import copy
import itertools
import os
import platform
import statistics
import sys
import tempfile
from pathlib import Path

import torch

from lfgnss.errors import INPUT_ERRORS
from lfgnss.metrics import markdown_table

from learning.train import exit_on_input_error, load_config, prepare, resolve_device, train

COLUMNS = ["device", "threads", "batch_size", "windows", "s_per_epoch", "windows_per_s", "speed_up",
           "val_rmse_3d_m"]


def time_settings(config: dict, devices: list[str], threads: list[int], batch_sizes: list[int], epochs: int,
                  progress: bool = True) -> list[dict]:
    """One row per (device, threads, batch size): median seconds per epoch after the first, and the last RMSE [m]."""
    if epochs < 2:
        raise ValueError(f"--epochs must be at least 2 (the first epoch is warm-up), got {epochs}")
    for d in devices:
        resolve_device(d)                                  # a missing GPU fails before any data loads
    prep = prepare(config)
    settings = list(itertools.product(devices, threads, batch_sizes))
    if progress:
        from tqdm import tqdm

        settings = tqdm(settings, desc="settings", file=sys.stderr)
    rows = []
    for device, n_threads, batch in settings:
        run = copy.deepcopy(config)
        run.update(device=device, threads=n_threads)
        run["train"].update(epochs=epochs, batch_size=batch)
        with tempfile.TemporaryDirectory() as tmp:
            history = train(run, tmp, progress=False, prepared=prep, export=False)
        seconds = statistics.median(h["seconds"] for h in history[2:])
        rows.append({"device": device, "threads": n_threads, "batch_size": batch, "windows": len(prep.windows),
                     "s_per_epoch": seconds, "windows_per_s": len(prep.windows) / seconds,
                     "val_rmse_3d_m": history[-1]["val_rmse_3d_m"]})
    for r in rows:
        r["speed_up"] = rows[0]["s_per_epoch"] / r["s_per_epoch"]
    return rows


def max_rmse_difference_m(rows: list[dict]) -> float:
    """Largest difference [m] of the last validation RMSE between settings of one batch size."""
    spread = [max(g) - min(g) for g in ([r["val_rmse_3d_m"] for r in rows if r["batch_size"] == b]
                                        for b in {r["batch_size"] for r in rows})]
    return max(spread)


def machine_line(devices: list[str]) -> str:
    """Where the figures were measured: torch, CPU count and any GPU."""
    gpus = sorted({torch.cuda.get_device_name(resolve_device(d)) for d in devices
                   if resolve_device(d).type == "cuda"})
    return (f"torch {torch.__version__}, Python {platform.python_version()}, {os.cpu_count()} CPU cores"
            + (f", GPU: {', '.join(gpus)}" if gpus else ", no GPU used"))


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    p = argparse.ArgumentParser(prog="python benchmarks/train_speed.py", description=__doc__.split("\n")[0])
    p.add_argument("--config", help="TOML configuration (default: built-in defaults)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a configuration key (repeatable)")
    p.add_argument("--device", action="append", help="cpu, cuda, cuda:N or auto (repeatable; default cpu)")
    p.add_argument("--threads", type=int, action="append", help="torch CPU threads (repeatable; default 1)")
    p.add_argument("--batch-size", type=int, action="append", help="windows per step (repeatable; default the "
                                                                    "configuration's)")
    p.add_argument("--epochs", type=int, default=3, help="epochs per setting, the first not timed (default 3)")
    p.add_argument("--out", help="also write the table to this Markdown file")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = p.parse_args(argv)
    devices, threads = args.device or ["cpu"], args.threads or [1]
    try:
        config = load_config(args.config, args.overrides)
        rows = time_settings(config, devices, threads, args.batch_size or [int(config["train"]["batch_size"])],
                             args.epochs, progress=not args.no_progress)
    except INPUT_ERRORS as exc:
        exit_on_input_error(p, exc)
    text = (f"Training speed of `{args.config or 'built-in defaults'}` ({', '.join(config['data']['datasets'])}; "
            f"{args.epochs} epochs per setting, median after the first). {machine_line(devices)}.\n\n"
            + markdown_table(rows, COLUMNS)
            + f"\nmax |dRMSE| between settings of one batch size: {max_rmse_difference_m(rows):.2e} m\n")
    if args.out:
        Path(args.out).write_text(text)
    print(text, end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
