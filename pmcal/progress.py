"""Progress display on stderr.

- On a terminal: a tqdm bar, and status lines above it.
- Piped (stderr not a terminal): silent, except for a long job (:func:`set_long`: a command whose input
  is large says so before its long steps), whose steps and status lines are printed as plain lines,
  one per step, so a log shows what a long run is doing.
- ``--quiet``: nothing. ``--verbose``: status lines also when piped.
- Warnings (:func:`warning`: something the user must know about the result, e.g. a rejected target):
  always on stderr, piped or not, unless ``--quiet``.
"""

from __future__ import annotations

import os
import sys
import time
from typing import Iterable, TypeVar

from tqdm.auto import tqdm

T = TypeVar("T")

_QUIET = False
_VERBOSE = False
_LONG = False


def set_quiet(quiet: bool) -> None:
    """Switch progress output off (``pmcal --quiet``)."""
    global _QUIET
    _QUIET = bool(quiet)


def set_verbose(verbose: bool) -> None:
    """More detail (``pmcal --verbose``): status lines also when stderr is not a terminal."""
    global _VERBOSE
    _VERBOSE = bool(verbose)


def set_long(long: bool) -> None:
    """Mark the running command as long (a large input): its steps are reported also when piped."""
    global _LONG
    _LONG = bool(long)


def quiet() -> bool:
    return _QUIET


def enabled() -> bool:
    """True when bars are drawn (a terminal, not ``--quiet``)."""
    return not _QUIET and sys.stderr.isatty()


def _lines() -> bool:
    """True when steps go to stderr as plain lines (piped, a long job, not ``--quiet``)."""
    return not _QUIET and _LONG and not sys.stderr.isatty()


class _LineBar:
    """The piped stand-in of a tqdm bar: one line on stderr per step (a new description, or a count for a
    bar whose description does not change)."""

    def __init__(self, iterable, total: int | None, desc: str, unit: str) -> None:
        self.iterable, self.total, self.desc, self.unit = iterable, total, desc, unit
        self.n = 0
        self.t0 = time.perf_counter()
        self.named = False              # set_description used: one line per description

    def _say(self, text: str) -> None:
        print(f"{text} ({time.perf_counter() - self.t0:.0f} s)", file=sys.stderr, flush=True)

    def set_description(self, desc: str) -> None:
        if desc != self.desc or not self.named:
            self.named = True
            self.desc = desc
            self._say(f"{desc}: step {min(self.n + 1, self.total or self.n + 1)} of {self.total}"
                      if self.total else desc)

    def update(self, n: int = 1) -> None:
        self.n += n
        if not self.named:
            self._say(f"{self.desc}: {self.n}/{self.total} {self.unit}s" if self.total else
                      f"{self.desc}: {self.n} {self.unit}s")

    def __iter__(self):
        for item in self.iterable:
            yield item
            self.update(1)

    def __enter__(self) -> "_LineBar":
        return self

    def __exit__(self, *exc) -> None:
        return None

    def close(self) -> None:
        return None


def progress(iterable: Iterable[T] | None = None, *, total: int | None = None, desc: str = "",
             unit: str = "it"):
    """Wrap ``iterable`` in a progress bar (or a disabled one): usable as iterator and context."""
    if _lines():
        return _LineBar(iterable, total, desc, unit)
    # a terminal that reports no size (a pty without a window, ``script``): tqdm would draw nothing in 0
    # columns and hide every bar below row 0, so assume 80 x 24
    sized = min(_terminal_size()) > 0
    return tqdm(iterable, total=total, desc=desc, unit=unit, disable=not enabled(),
                leave=False, file=sys.stderr, dynamic_ncols=sized, ncols=None if sized else 80,
                nrows=None if sized else 24)


def _terminal_size() -> tuple[int, int]:
    """(columns, lines) of the terminal stderr writes to; (0, 0) when it reports none."""
    try:
        return tuple(os.get_terminal_size(sys.stderr.fileno()))
    except (OSError, ValueError, AttributeError):
        return 0, 0


def status(message: str) -> None:
    """One status line on stderr for a long step (suppressed like the bars)."""
    if _lines():
        print(message, file=sys.stderr, flush=True)
    elif enabled() or (_VERBOSE and not _QUIET):
        tqdm.write(message, file=sys.stderr)


def warning(message: str) -> None:
    """One ``pmcal: warning: ...`` line on stderr, piped or not, unless ``--quiet`` (docs/formats.md,
    "What the commands print"): for what the user must know about a result (a rejected target, a row
    left out), not for progress."""
    if _QUIET:
        return
    line = f"pmcal: warning: {message}"
    if enabled():
        tqdm.write(line, file=sys.stderr)
    else:
        print(line, file=sys.stderr, flush=True)
