"""``python -m lfgnss``: list the commands; ``python -m lfgnss COMMAND ...`` runs one (``solve``, ``train``...)."""
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
    """Print the commands (exit 0), or the version (--version); ``COMMAND ARGS...`` runs that command's main with ARGS
    (``solve`` is ``python -m lfgnss.solve``); anything else: one line on stderr naming the commands, exit 2."""
    args = sys.argv[1:] if argv is None else list(argv)
    if args and args[0] == "--version":
        from . import __version__

        print(f"lfgnss {__version__}")
        return 0
    if args and args[0] not in ("-h", "--help"):
        wanted = [m for m in COMMANDS if m.split(".")[1] == args[0]]
        if wanted:
            import importlib

            return importlib.import_module(wanted[0]).main(args[1:])
        every = ", ".join(f"python -m {m}" for m in COMMANDS)
        print(f"python -m lfgnss: error: unknown command {args[0]!r}; the commands: {every} (or python -m lfgnss "
              f"solve ..., train ...)", file=sys.stderr)
        return 2
    from .errors import print_stdout

    print_stdout("lfgnss commands (python -m lfgnss COMMAND ... runs one too):\n"
                 + "".join(f"  python -m {m:<19}{text}\n" for m, text in COMMANDS.items()), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
