"""Errors the CLI turns into one clear line and an exit code.

``BadInput`` (exit 2) is for anything the user can fix: an unknown name, a bad value, a
missing or corrupted file. Anything else that escapes a command is a runtime failure (exit 1).
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable


class BadInput(ValueError):
    """The user's input is wrong; the message says what to do. Exit code 2."""

    exit_code = 2


class RunFailure(RuntimeError):
    """A command failed for a reason that is not the user's input. Exit code 1."""

    exit_code = 1


def suggest(name: str, choices: Iterable[str]) -> str:
    """' (did you mean X?)' for the closest of ``choices``, or ''."""
    choices = list(choices)
    close = difflib.get_close_matches(str(name), choices, n=1, cutoff=0.5)
    if not close:
        return ""
    # a second suggestion only when it is about as close as the first
    close += [c for c in difflib.get_close_matches(str(name), choices, n=2, cutoff=0.8) if c not in close][:1]
    return " (did you mean " + " or ".join(repr(c) for c in close) + "?)"


def unknown(kind: str, name: str, choices: Iterable[str]) -> BadInput:
    """A BadInput for an unknown name, with the closest matches and the valid names."""
    choices = sorted(choices)
    valid = ", ".join(choices) if choices else "none installed"
    return BadInput(f"unknown {kind} {name!r}{suggest(name, choices)}; valid: {valid}")
