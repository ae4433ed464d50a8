"""What the commands share: number parsers for argparse, messages on stderr, progress, outputs."""
from __future__ import annotations

import argparse
import math
import sys

from ..progress import Progress

__all__ = ["add_quiet", "finite", "positive", "progress_for", "say"]


def say(args, msg):
    """A message on stderr unless ``--quiet``."""
    if not getattr(args, "quiet", False):
        print(msg, file=sys.stderr, flush=True)


def progress_for(args, label) -> Progress:
    """The progress bar with ETA of a command (silent with ``--quiet``)."""
    return Progress(label, quiet=getattr(args, "quiet", False))


def add_quiet(p):
    p.add_argument("--quiet", action="store_true", help="no progress or messages on stderr")


def positive(name):
    """argparse type: a finite number > 0 (the message names the option)."""
    def parse(text):
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number, got {text!r}") from None
        if not (math.isfinite(v) and v > 0):
            raise argparse.ArgumentTypeError(f"{name} must be a positive number, got {text}")
        return v
    return parse


def count(name, least=1):
    """argparse type: a whole number >= ``least`` (the message names the option)."""
    def parse(text):
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a whole number, got {text!r}") from None
        if v < least:
            raise argparse.ArgumentTypeError(f"{name} must be at least {least}, got {text}")
        return v
    return parse


def finite(name):
    """argparse type: a finite number (the message names the option)."""
    def parse(text):
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be a number, got {text!r}") from None
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"{name} must be finite, got {text}")
        return v
    return parse
