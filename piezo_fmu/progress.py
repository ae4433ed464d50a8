"""Progress of long work, with an estimate of the time left, for people watching a terminal.

The library reports progress through a plain callable, ``progress(fraction, message="")``
(``fraction`` in 0..1 or ``None`` when unknown; ``message`` names the current stage), so that any
caller can pass its own. :class:`Progress` is the one the command line passes: a bar that redraws
itself on a terminal, and occasional plain lines when stderr is a file or a pipe (a CI log gets a
line every ``log_interval`` seconds, not thousands of carriage returns).
"""
from __future__ import annotations

import math
import sys
import time

__all__ = ["Progress", "format_seconds"]


def format_seconds(s: float) -> str:
    """``s`` seconds as ``12.3 s``, ``4 min 05 s`` or ``1 h 02 min``."""
    if not math.isfinite(s):
        return "?"
    if s < 60:
        return f"{s:.1f} s"
    if s < 3600:
        return f"{int(s // 60)} min {int(s % 60):02d} s"
    return f"{int(s // 3600)} h {int(s % 3600 // 60):02d} min"


class Progress:
    """``progress(fraction, message="")``: a progress line with elapsed time and ETA on stderr.

    Parameters
    ----------
    label : str
        What is running (the command's name).
    quiet : bool
        Print nothing at all.
    stream : file, optional
        Where to write (default ``sys.stderr``).
    interval : float
        Least time between two redraws of the bar on a terminal [s].
    log_interval : float
        Least time between two lines when the stream is not a terminal [s]; a new stage
        (``message``) is always written.
    """

    WIDTH = 24

    def __init__(self, label, quiet=False, stream=None, interval=0.2, log_interval=10.0):
        self.label = label
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = not quiet
        isatty = getattr(self.stream, "isatty", None)
        self.tty = bool(isatty and isatty())
        self.interval = interval if self.tty else log_interval
        self.t0 = time.perf_counter()
        self.last = -math.inf
        self.message = ""
        self.fraction = 0.0
        self.done = False
        self._open_line = False
        self._stage_start = (self.t0, 0.0)

    def eta(self, fraction: float, now: float) -> float:
        """Seconds left at the rate since the current stage began (``inf`` until 1 % more is done),
        so that a slow start (a compiler, a build) does not inflate the estimate."""
        t_stage, f_stage = self._stage_start
        if fraction - f_stage < 0.01:
            return math.inf
        return (now - t_stage) * (1.0 - fraction) / (fraction - f_stage)

    def __call__(self, fraction=None, message=""):
        if not self.enabled or self.done:
            return
        now = time.perf_counter()
        new_stage = bool(message) and message != self.message
        if message:
            self.message = message
        if fraction is not None:
            self.fraction = min(max(float(fraction), 0.0), 1.0)
        if new_stage:
            self._stage_start = (now, self.fraction)
        finished = fraction is not None and self.fraction >= 1.0 and not message
        if not (new_stage or finished or now - self.last >= self.interval):
            return
        self.last = now
        elapsed = now - self.t0
        if finished:
            self._write(f"{self.label}: done in {format_seconds(elapsed)}", final=True)
            self.done = True
            return
        if fraction is None:          # a stage without a known share of the work: a line of its own
            self._write(f"{self.label}: {self.message} ({format_seconds(elapsed)})", final=True)
            return
        text = f"{100 * self.fraction:5.1f} %, {format_seconds(elapsed)}, ETA " \
               f"{format_seconds(self.eta(self.fraction, now))}"
        if self.tty:
            n = int(self.WIDTH * self.fraction)
            bar = "#" * n + "." * (self.WIDTH - n)
            self._write(f"{self.label} [{bar}] {text}" + (f"  {self.message}" if self.message else ""))
        else:
            self._write(f"{self.label}: {text}" + (f" - {self.message}" if self.message else ""), final=True)

    def note(self, message):
        """A stage message on its own line (the bar, if any, is redrawn after it)."""
        if not self.enabled:
            return
        if self._open_line:
            self.stream.write("\n")
            self._open_line = False
        self.stream.write(f"{message}\n")
        self.stream.flush()

    def close(self):
        """End the bar's line (call when the work ends early or without a final ``1.0``)."""
        if self._open_line:
            self.stream.write("\n")
            self.stream.flush()
            self._open_line = False

    def _write(self, text, final=False):
        if self.tty:
            self.stream.write("\r\x1b[K" + text + ("\n" if final else ""))
            self._open_line = not final
        else:
            self.stream.write(text + "\n")
        self.stream.flush()
