"""Command-line help without the reST markup the docstrings it is taken from use."""
from __future__ import annotations

import argparse


class PlainHelp(argparse.HelpFormatter):
    """argparse's formatter with the docstrings' ``literal`` quotes removed from descriptions, epilogs and option help
    (a terminal shows them as double backquotes)."""

    def _format_text(self, text: str) -> str:
        return super()._format_text(text.replace("``", ""))

    def _expand_help(self, action: argparse.Action) -> str:
        return super()._expand_help(action).replace("``", "")


class PlainHelpWithDefaults(PlainHelp, argparse.ArgumentDefaultsHelpFormatter):
    """``PlainHelp`` that also shows each option's default."""
