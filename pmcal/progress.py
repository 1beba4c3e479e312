"""Progress display: a tqdm bar on a terminal, silent with ``--quiet`` or when stderr is not a TTY."""

from __future__ import annotations

import sys
from typing import Iterable, TypeVar

from tqdm.auto import tqdm

T = TypeVar("T")

_QUIET = False
_VERBOSE = False


def set_quiet(quiet: bool) -> None:
    """Switch progress output off (``pmcal --quiet``)."""
    global _QUIET
    _QUIET = bool(quiet)


def set_verbose(verbose: bool) -> None:
    """More detail (``pmcal --verbose``): status lines also when stderr is not a terminal."""
    global _VERBOSE
    _VERBOSE = bool(verbose)


def quiet() -> bool:
    return _QUIET


def enabled() -> bool:
    return not _QUIET and sys.stderr.isatty()


def progress(iterable: Iterable[T] | None = None, *, total: int | None = None, desc: str = "",
             unit: str = "it") -> "tqdm":
    """Wrap ``iterable`` in a progress bar (or a disabled one): usable as iterator and context."""
    return tqdm(iterable, total=total, desc=desc, unit=unit, disable=not enabled(),
                leave=False, file=sys.stderr, dynamic_ncols=True)


def status(message: str) -> None:
    """One status line on stderr for a long step (suppressed like the bars)."""
    if enabled() or (_VERBOSE and not _QUIET):
        tqdm.write(message, file=sys.stderr)
