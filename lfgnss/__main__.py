"""``python -m lfgnss``: list the commands."""
from __future__ import annotations

import sys

#: Each command's module and what it does.
COMMANDS = {"lfgnss.solve": "position a RINEX file (EKF, factor graph or least squares)",
            "lfgnss.datasets": "build benchmark datasets, check truth alignment and the coarse fix",
            "lfgnss.summary": "feature statistics and plots per dataset",
            "lfgnss.benchmark": "every estimator against RTKLIB on the test splits",
            "learning.train": "train the LF-GNSS network",
            "learning.crossval": "blocked K-fold cross-validation of a training recipe",
            "learning.export": "export a training checkpoint as a model file, or describe one (--show)"}


def main(argv: list[str] | None = None) -> int:
    """Print the commands (exit 0); any argument but -h/--help: one line on stderr naming the command to run, exit 2."""
    args = sys.argv[1:] if argv is None else list(argv)
    if args and args[0] not in ("-h", "--help"):
        wanted = [m for m in COMMANDS if m.split(".")[1] == args[0]]
        every = ", ".join(f"python -m {m}" for m in COMMANDS)
        hint = f"run python -m {wanted[0]}" if wanted else f"the commands: {every}"
        print(f"python -m lfgnss: error: unknown argument {args[0]!r} (this only lists the commands); {hint}",
              file=sys.stderr)
        return 2
    print("lfgnss commands:\n" + "".join(f"  python -m {m:<19}{text}\n" for m, text in COMMANDS.items()), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
