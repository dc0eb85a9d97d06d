"""Argument types of the `sonicverse` command: every value is checked when the command line is parsed, before any
long work starts, so a mistake costs one line (``sonicverse: error: argument --seconds: ...``) and exit code 2.

Each factory returns a callable for argparse's ``type=``; it raises ``argparse.ArgumentTypeError`` with a message that
says what is allowed.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

from sonicverse_core.errors import ConfigError


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line on stderr and exit code 2 (no usage block): the house rule for
    every user mistake. ``--help`` still prints the full usage."""

    def error(self, message: str):  # noqa: D401 - argparse's hook
        first = message.strip().splitlines()[0] if message.strip() else "bad arguments"
        print(f"sonicverse: error: {first} (see '{self.prog} --help')", file=sys.stderr)
        raise SystemExit(2)


def count(lo: int = 1, hi: int = 10**9, what: str = "an integer"):
    """An integer within [lo, hi]."""

    def parse(text: str) -> int:
        try:
            v = int(text, 10)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what} within {lo}..{hi}, got '{text}'") from None
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"expected {what} within {lo}..{hi}, got {v}")
        return v

    parse.__name__ = "integer"
    return parse


seed = count(0, 2**63 - 1, "a seed (an integer >= 0)")


def number(lo: float = -math.inf, hi: float = math.inf, lo_open: bool = False, unit: str = ""):
    """A finite float within [lo, hi] (or (lo, hi] with ``lo_open``)."""
    left = "(" if lo_open else "["
    span = f"{left}{lo:g}, {hi:g}]" + (f" {unit}" if unit else "")

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number in {span}, got '{text}'") from None
        if not math.isfinite(v) or v < lo or v > hi or (lo_open and v == lo):
            raise argparse.ArgumentTypeError(f"expected a finite number in {span}, got '{text}'")
        return v

    parse.__name__ = "number"
    return parse


def _writable_parent(p: Path) -> None:
    """The nearest existing ancestor of ``p`` must be a writable folder (the rest is created when writing)."""
    a = p.parent.resolve() if str(p.parent) else Path.cwd()
    while not a.exists():
        a = a.parent
    if not a.is_dir():
        raise argparse.ArgumentTypeError(f"cannot create '{p}': '{a}' is a file, not a folder")
    if not os.access(a, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"cannot write '{p}': folder '{a}' is not writable")


def out_file(*suffixes: str):
    """A file to write: one of ``suffixes`` (lower case, with the dot), not a folder, in a writable place."""

    def parse(text: str) -> str:
        p = Path(text)
        if not text or text.endswith(("/", os.sep)) or p.is_dir():
            raise argparse.ArgumentTypeError(f"'{text}' is a folder; give a file name ending in "
                                             f"{' or '.join(suffixes)}")
        if suffixes and p.suffix.lower() not in suffixes:
            raise argparse.ArgumentTypeError(f"unsupported format '{p.suffix or '(none)'}' for '{text}': use "
                                             f"{' or '.join(suffixes)}")
        _writable_parent(p)
        return text

    parse.__name__ = "file"
    return parse


def out_dir(text: str) -> str:
    """A folder to write into: not an existing file, in a writable place (created when needed)."""
    p = Path(text)
    if not text:
        raise argparse.ArgumentTypeError("empty folder name")
    if p.exists() and not p.is_dir():
        raise argparse.ArgumentTypeError(f"'{text}' is a file, not a folder")
    if p.exists():
        if not os.access(p, os.W_OK | os.X_OK):
            raise argparse.ArgumentTypeError(f"folder '{text}' is not writable")
    else:
        _writable_parent(p)
    return text


def in_file(*suffixes: str):
    """An existing, readable file (optionally one of ``suffixes``)."""

    def parse(text: str) -> str:
        p = Path(text)
        if not p.is_file():
            raise argparse.ArgumentTypeError(f"no such file: '{text}'" if not p.exists() else
                                             f"'{text}' is not a file")
        if suffixes and p.suffix.lower() not in suffixes:
            raise argparse.ArgumentTypeError(f"'{text}': expected a {' or '.join(suffixes)} file")
        if not os.access(p, os.R_OK):
            raise argparse.ArgumentTypeError(f"'{text}' is not readable")
        return text

    parse.__name__ = "file"
    return parse


def xyz(text: str, n=(3,)) -> list[float]:
    """'X,Y,Z' (or another of the counts ``n``) of finite numbers."""
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        raise ConfigError(f"expected comma-separated numbers, got '{text}'") from None
    if len(v) not in n or not all(math.isfinite(x) for x in v):
        raise ConfigError(f"expected {' or '.join(map(str, n))} finite numbers, got '{text}'")
    return v


def size(text: str) -> tuple[int, int]:
    """'WIDTHxHEIGHT' in pixels, 16-8192 per side."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"eye size must be WIDTHxHEIGHT, got '{text}'") from None
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise ConfigError(f"eye size must be 16-8192 pixels per side, got {w}x{h}")
    return w, h


def argtype(fn):
    """An argparse type from a parser that raises ConfigError (checked at parse time, same one-line message)."""

    def parse(text: str):
        try:
            return fn(text)
        except ConfigError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    parse.__name__ = getattr(fn, "__name__", "value")
    return parse
