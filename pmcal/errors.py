"""The one exception type for bad user input.

Every reader of user files raises :class:`InputError` naming the file, the row and the field, so the
CLI can print one clear line and exit with status 2.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass


@dataclass
class InputError(Exception):
    """Bad input from the user: a file, a row in it, a field of that row, and what is wrong.

    ``row`` counts data rows from 1 (the header and ``#`` comment lines are not counted), so the
    message points at the row a person sees in a spreadsheet after the header.
    """

    message: str
    file: str | None = None
    row: int | None = None
    field: str | None = None

    def __str__(self) -> str:
        where = []
        if self.file:
            where.append(str(self.file))
        if self.row is not None:
            where.append(f"row {self.row}")
        if self.field:
            where.append(f"field '{self.field}'")
        return (": ".join([", ".join(where), self.message]) if where else self.message)

    def __post_init__(self) -> None:
        Exception.__init__(self, str(self))


@contextlib.contextmanager
def for_option(option: str) -> Iterator[None]:
    """Inside, an :class:`InputError` that names no field is about the file given to ``option``: name it."""
    try:
        yield
    except InputError as exc:
        if exc.field is None:
            raise InputError(exc.message, file=exc.file, row=exc.row, field=option) from None
        raise


class RunError(Exception):
    """A failure while doing the work (not the user's input): printed as one line, exit status 1."""
