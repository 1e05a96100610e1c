"""Where a trained model came from: the command, the code's git commit, and the dataset TOMLs it read.

A training run records ``run_record(command, config)`` in its checkpoints (a resumed run appends its own to
``resumes``), and ``learning.export`` copies it into the model file's metadata as ``provenance``, so a model file
says how to make it again without the run folder beside it.
"""
from __future__ import annotations

import datetime as _dt
import shlex
import subprocess
from pathlib import Path

#: The repository the running code is in (a git checkout for a development install; else no commit is recorded).
CODE_ROOT = Path(__file__).resolve().parents[1]


def git_state(root: str | Path = CODE_ROOT, ignore: tuple[str | Path, ...] = ()) -> dict | None:
    """{"commit": 40 hex digits, "dirty": tracked files modified} of the checkout at ``root``; None if not one.

    Changes under ``ignore`` (a run's own output folders, where inside the checkout) do not count as dirty.
    """
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, check=True,
                              timeout=10).stdout.strip()

    top = Path(root).resolve()
    inside = [q for q in (Path(p).resolve() for p in ignore) if q == top or top in q.parents]
    try:
        commit = git("rev-parse", "--verify", "HEAD")
        dirty = bool(git("status", "--porcelain", "--untracked-files=no", "--", ".",
                         *(f":(exclude){q}" for q in inside)))
    except (OSError, subprocess.SubprocessError):      # no git, not a checkout, a hung filesystem
        return None
    return {"commit": commit, "dirty": dirty}


def code_text(git: dict | None) -> str:
    """``git_state``'s result in words: "git 0123456789ab", "... with uncommitted changes", or not a checkout."""
    if not git:
        return "code not in a git checkout"
    return f"git {git['commit'][:12]}{' with uncommitted changes' if git.get('dirty') else ''}"


def command_line(prog: str, argv: list[str]) -> str:
    """The shell command that ran ``prog`` with ``argv``, quoted so it can be pasted back."""
    return " ".join([prog, *map(shlex.quote, argv)])


def registered_tomls(config: dict) -> dict[str, str]:
    """Path -> text of each dataset TOML the run's ``data.register`` names (unreadable ones: the error)."""
    out = {}
    for path in (config.get("data") or {}).get("register") or []:
        try:
            out[str(path)] = Path(path).read_text()
        except (OSError, UnicodeDecodeError) as err:
            out[str(path)] = f"(not readable: {err})"
    return out


def run_record(command: str | None, config: dict) -> dict:
    """What one training run (or resumption) records: command, working folder, git state, dataset TOMLs, time."""
    return {"command": command, "cwd": str(Path.cwd()), "git": git_state(),
            "dataset_tomls": registered_tomls(config),
            "started_utc": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")}


def describe(provenance: dict | None) -> list[str]:
    """Readable lines for ``python -m learning.export --show``: how the model was made, resumptions included."""
    if not provenance:
        return ["provenance: not recorded (a model trained before lfgnss recorded it: see the model README for its "
                "command)"]
    lines = []
    for label, rec in [("trained", provenance)] + [("resumed", r) for r in provenance.get("resumes", [])]:
        lines.append(f"{label} {rec.get('started_utc', '?')} in {rec.get('cwd', '?')}, {code_text(rec.get('git'))}")
        lines.append(f"  command: {rec.get('command') or '(called from Python, no command line)'}")
        for path in rec.get("dataset_tomls") or {}:
            lines.append(f"  dataset TOML: {path} (its text is in the file)")
    return lines
