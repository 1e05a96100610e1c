"""Exceptions with one-line messages that name the file (and line) at fault."""
from __future__ import annotations

import contextlib
import difflib
import os
import sys
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path


class LfgnssError(Exception):
    """Base class of every error lfgnss raises on bad input."""


class RinexError(LfgnssError):
    """A RINEX file that cannot be used: ``PATH:LINE: reason``."""

    def __init__(self, path: str | Path, reason: str, line: int | None = None) -> None:
        self.path, self.reason, self.line = str(path), reason, line
        where = f"{self.path}:{line}" if line is not None else self.path
        super().__init__(f"{where}: {reason}")


class InputError(LfgnssError):
    """Any other unusable input file (truth, model, configuration): ``PATH[:LINE]: reason``."""

    def __init__(self, path: str | Path, reason: str, line: int | None = None) -> None:
        self.path, self.reason, self.line = str(path), reason, line
        where = f"{self.path}:{line}" if line is not None else self.path
        super().__init__(f"{where}: {reason}")


class UnknownNameError(KeyError):
    """An unknown name (a back end, a dataset id): a KeyError whose message prints as written, without the quotes
    ``str(KeyError)`` adds."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


def closest_name(name: str, known: list[str]) -> str | None:
    """The one of ``known`` a mistyped ``name`` most likely means: the same in another case, else the closest
    (``difflib``, in the case given, then in lower case), else one with the same last dotted part; None if none is."""
    name = str(name)
    close = ([k for k in known if k.lower() == name.lower()] or difflib.get_close_matches(name, known, n=1)
             or difflib.get_close_matches(name.lower(), known, n=1)
             or [k for k in known if k.split(".")[-1] == name.split(".")[-1]])
    return close[0] if close else None


def did_you_mean(name: str, known: list[str]) -> str:
    """`` (did you mean 'x'?)`` for :func:`closest_name`, or ""."""
    close = closest_name(name, known)
    return f" (did you mean {close!r}?)" if close is not None else ""


#: What the command lines report as bad input (a file, a setting, a dataset id): one line, exit status 2.
INPUT_ERRORS = (LfgnssError, FileNotFoundError, KeyError, ValueError)


def one_line(exc: BaseException) -> str:
    """The exception's message on one line (without the quotes a KeyError adds, and without line breaks)."""
    text = exc.args[0] if isinstance(exc, KeyError) and len(exc.args) == 1 and isinstance(exc.args[0], str) else str(exc)
    return " ".join(text.split()) or type(exc).__name__


def shortened(text: str, limit: int) -> str:
    """``text`` cut to ``limit`` characters, ending in ``...`` where cut (a command line, a torch message)."""
    return text if len(text) <= limit else text[:limit - 3] + "..."


def stdout_gone() -> None:
    """After a BrokenPipeError on stdout (the reader of ``| head`` went away): point stdout at the null device, so
    that nothing more, the interpreter's last flush included, fails on it."""
    os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def print_stdout(text: str, end: str = "\n") -> None:
    """Print ``text`` on stdout, flushed; where its reader went away (``| head``), nothing more goes there
    (``stdout_gone``) and the command goes on, as if it had been read."""
    try:
        print(text, end=end, flush=True)
    except BrokenPipeError:
        stdout_gone()


def cannot_write(err: OSError) -> str:
    """The reason an output could not be written, ``cannot write (REASON)``; its file is ``err.filename``."""
    return f"cannot write ({err.strerror or one_line(err)})"


def input_line(exc: BaseException) -> str:
    """One line for bad input; an OSError with a file name as ``FILE: reason`` (not ``[Errno 36] ...: 'FILE'``),
    saying so where the file is the cache folder ``$LFGNSS_CACHE`` or inside it."""
    import os

    if isinstance(exc, OSError) and exc.filename:
        cache = os.environ.get("LFGNSS_CACHE")
        name = Path(str(exc.filename))
        what = " (the cache folder, $LFGNSS_CACHE)" if cache and Path(cache) in (name, *name.parents) else ""
        return f"{exc.filename}{what}: {exc.strerror or one_line(exc)}"
    return one_line(exc)


def path_option(text: str) -> Path:
    """argparse type of a path option: an empty one (``--out "$UNSET"``) is refused rather than read as ``.``."""
    import argparse

    if not text.strip():
        raise argparse.ArgumentTypeError("needs a path, got an empty string")
    return Path(text)


def print_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """``warnings.showwarning`` of the command lines: ``warning: MESSAGE`` on one line of stderr."""
    print(f"warning: {' '.join(str(message).split())}", file=sys.stderr)


@contextlib.contextmanager
def warnings_on_one_line() -> Iterator[None]:
    """Within: each warning is printed as :func:`print_warning` does, not as Python's two lines with a source line."""
    with warnings.catch_warnings():
        warnings.showwarning = print_warning
        yield


def run_command(work: Callable[[], int], what: str) -> int:
    """``work()``'s exit status, as every command line ends: bad input is one line ``error: ...`` and 2, Ctrl-C
    ``interrupted`` and 130, a bug one line ``error: internal error in WHAT (...)`` and 3; warnings one line each."""
    try:
        with warnings_on_one_line():
            warnings.simplefilter("ignore", FutureWarning)
            return work()
    except (*INPUT_ERRORS, OSError) as err:
        print(f"error: {input_line(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as err:  # a bug, not bad input: still one line, no traceback, a distinct exit code
        print(f"error: internal error in {what} ({type(err).__name__}: {one_line(err)}); please report it",
              file=sys.stderr)
        return 3
