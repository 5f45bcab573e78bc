"""The command line's parser class and value converters: numbers (that may use ``pi``), whole numbers,
starts (``--ic``) and triples, each refusing a bad value with the flag's name and an example."""
from __future__ import annotations

import argparse
import math

import numpy as np

from ..files.npz import load_ics
from ..files.npz import parse_number as _number

__all__ = ["UsageError", "Parser", "number", "whole", "parse_ic", "parse_triple", "ics_from_args"]


class UsageError(ValueError):
    """An argparse usage error, reported like any other bad input."""


class Parser(argparse.ArgumentParser):
    """ArgumentParser that raises instead of exiting, so ``main`` returns an exit code."""

    def error(self, message):
        raise UsageError(f"{message} (see '{self.prog} --help')")


# ---------------------------------------------------------------------------------------------
# values
# ---------------------------------------------------------------------------------------------

def number(flag: str, example: str, *, positive: bool = True, nonnegative: bool = False):
    """argparse ``type=``: a finite number (may use ``pi``), ``> 0`` by default."""
    def conv(text):
        try:
            v = _number(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} must be a number, got {text!r} (e.g. {flag} {example})")
        if not math.isfinite(v) or (positive and not v > 0) or (nonnegative and v < 0):
            need = "> 0" if positive else ">= 0" if nonnegative else "finite"
            raise argparse.ArgumentTypeError(f"{flag} must be a finite number {need}, got {text!r} "
                                             f"(e.g. {flag} {example})")
        return v
    return conv


def whole(flag: str, example: str, minimum: int = 1, maximum: int = 2**31 - 2):
    """argparse ``type=``: a whole number in ``[minimum, maximum]``."""
    def conv(text):
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{flag} must be a whole number, got {text!r} (e.g. {flag} {example})")
        if v < minimum:
            raise argparse.ArgumentTypeError(f"{flag} must be >= {minimum}, got {v} (e.g. {flag} {example})")
        if v > maximum:
            raise argparse.ArgumentTypeError(f"{flag} must be <= {maximum}, got {v} (e.g. {flag} {example})")
        return v
    return conv


def parse_ic(text: str) -> list[float]:
    """``'X,Y,THETA'`` or ``'X,Y,THETA,P1,P2'`` -> list of floats (entries may use ``pi``)."""
    hint = ("expected X,Y,THETA or X,Y,THETA,P1,P2 separated by commas, e.g. --ic=-3,-2,pi/8 "
            "(write --ic=... when the first number is negative)")
    parts = text.split(",")
    if len(parts) not in (3, 5):
        raise ValueError(f"could not parse --ic {text!r}: got {len(parts)} entries; {hint}")
    try:
        vals = [_number(s) for s in parts]
    except ValueError as e:
        raise ValueError(f"could not parse --ic {text!r}: {e}; {hint}") from None
    if not all(math.isfinite(v) for v in vals):
        raise ValueError(f"--ic {text!r} has a non-finite entry; give finite numbers, e.g. --ic 1,1,0.5")
    return vals


def parse_triple(text: str, flag: str, example: str) -> tuple[float, float, float]:
    parts = text.split(",")
    try:
        if len(parts) != 3:
            raise ValueError(f"got {len(parts)} entries")
        return tuple(_number(s) for s in parts)
    except ValueError as e:
        raise ValueError(f"could not parse {flag} {text!r}: {e}; expected three comma-separated "
                         f"numbers, e.g. {flag} {example}") from None


def ics_from_args(args) -> np.ndarray:
    """Starts from ``--ics FILE`` or repeated ``--ic X,Y,THETA[,P1,P2]``."""
    if args.ics is not None:
        return load_ics(args.ics, hint="use --ic X,Y,THETA")
    rows = [parse_ic(s) for s in args.ic]
    width = max(len(r) for r in rows)
    rows = [r + [0.0] * (width - len(r)) for r in rows]
    return np.asarray(rows, dtype=np.float64)
