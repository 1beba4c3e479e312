"""Atomic file output: write to a temporary file beside the target, then rename.

Nothing is half-written: if the writer raises, the temporary file is removed and the target is left
as it was (absent, or its previous content).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import IO, Iterator

from pmcal.errors import InputError

#: File pmcal leaves in every folder it writes; a folder without it holds the user's files and is never
#: replaced unless the user says ``--force``.
MARKER = ".pmcal-output"


def _default_mode() -> int:
    """Permissions of a newly created file under the current umask (mkstemp would give 0600)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask




@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w", encoding: str | None = "utf-8",
                 newline: str | None = "") -> Iterator[IO]:
    """Open a temporary file for writing; on success rename it to ``path`` (same directory)."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    binary = "b" in mode
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, mode, **({} if binary else {"encoding": encoding, "newline": newline})) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, _default_mode())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _json_default(o):
    if hasattr(o, "tolist"):          # numpy arrays and scalars
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def read_json(path: str | os.PathLike) -> object:
    """The JSON document in ``path`` (a byte-order mark accepted); :class:`InputError` naming the file for a
    missing, unreadable or malformed file (with the line and column of a syntax error)."""
    text = read_text(path)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})", file=str(path)) from None


def check_param_values(params: dict, path: str, unit_of, limits: dict[str, float], prefix: str = "params."
                       ) -> dict[str, float]:
    """The values of a parameters JSON's ``params`` object: each a finite number (not a boolean) whose
    magnitude is at most ``limits[unit_of(key)]`` (beyond it a unit mix-up, radians or micrometres, is far
    likelier than such a geometric error). Returns them as floats; an :class:`InputError` names the file
    and the field ``prefix + key``."""
    out = {}
    for key, value in params.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise InputError(f"value {value!r} is not a finite number", file=path, field=prefix + key)
        unit = unit_of(key)
        if abs(value) > limits[unit]:
            raise InputError(f"{value:g} {unit} is implausible for a geometric error (at most {limits[unit]:g} "
                             f"{unit}; units are mm and degrees)", file=path, field=prefix + key)
        out[key] = float(value)
    return out


def write_json(path: str | os.PathLike, doc, indent: int = 2) -> None:
    """Write a JSON document atomically; numpy arrays and scalars become plain JSON values."""
    with atomic_write(path) as fh:
        json.dump(doc, fh, indent=indent, default=_json_default)
        fh.write("\n")


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike) -> Iterator[Path]:
    """Build a directory in a temporary sibling; on success replace ``path`` with it."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    try:
        yield tmp
        mode = _default_mode()
        os.chmod(tmp, mode | ((mode & 0o444) >> 2))     # directories: x where r is granted
        (tmp / MARKER).write_text("written by pmcal; the whole folder is replaced on the next run\n",
                                  encoding="utf-8")
        if target.exists():
            shutil.rmtree(target)
        os.replace(tmp, target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def read_text(path: str | os.PathLike, field: str | None = None) -> str:
    """The text of a UTF-8 file (a BOM is dropped); :class:`InputError` naming the file when it is missing,
    unreadable, or not UTF-8 (then the byte and the fix: save it as UTF-8)."""
    p = str(path)
    try:
        return Path(path).read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputError("file not found", file=p, field=field) from None
    except UnicodeDecodeError as exc:
        line = exc.object[: exc.start].count(b"\n") + 1
        raise InputError(f"not UTF-8 text (byte 0x{exc.object[exc.start]:02X} on line {line}, another encoding "
                         "such as Latin-1 or Windows-1252?): save it as UTF-8", file=p, field=field) from None
    except IsADirectoryError:
        raise InputError("is a folder, not a file", file=p, field=field) from None
    except OSError as exc:
        raise InputError(f"cannot read file ({exc.strerror or exc})", file=p, field=field) from None


def check_output(path: str | os.PathLike, *, folder: bool = False, force: bool = False,
                 field: str | None = None, suffixes: tuple[str, ...] = ()) -> None:
    """Check before any work that ``path`` can be written; raise :class:`InputError` otherwise.

    A file output must not be a folder, must not be a read-only file, and its folder must exist and be
    writable. A folder output (``folder=True``) must not be a file; if it exists, it must hold the marker
    :data:`MARKER` (pmcal wrote it, so replacing it loses nothing of the user's) or be empty, unless
    ``force``. A file output's name must end in one of ``suffixes`` (its format's; any when empty).
    """
    if path is None:
        return
    target = Path(path)
    parent = target.parent if str(target.parent) else Path(".")
    if not str(path).strip():
        raise InputError("empty output path", field=field)
    if not parent.is_dir():
        what = "is not a folder" if parent.exists() else "does not exist"
        raise InputError(f"cannot write {target}: the folder {parent} {what}", field=field)
    if not _writable(parent):
        raise InputError(f"cannot write {target}: the folder {parent} is not writable", field=field)
    if folder:
        if target.exists() and not target.is_dir():
            raise InputError(f"{target} is a file, not a folder", field=field)
        if target.is_dir() and not (target / MARKER).exists() and any(target.iterdir()) and not force:
            raise InputError(f"{target} exists and was not written by pmcal (no {MARKER}); it would be "
                             "replaced: choose another folder or add --force", field=field)
        return
    if target.is_dir():
        raise InputError(f"{target} is a folder; give a file name", field=field)
    if target.exists() and not _writable(target):
        raise InputError(f"{target} is read-only; it will not be replaced", field=field)
    if suffixes and target.suffix.lower() not in suffixes:
        raise InputError(f"{target}: this output is {' or '.join(s.lstrip('.').upper() for s in suffixes)}; "
                         f"name it with {' or '.join(suffixes)}", field=field)


def check_not_input(path: str | os.PathLike, inputs, *, field: str | None = None) -> None:
    """Raise :class:`InputError` when the output ``path`` is the same file as one of ``inputs`` ((option,
    path) pairs): the same resolved path, or the same inode (a hard link, a symlink). Checked whatever
    ``--force`` says: replacing an input with an output loses the input."""
    target = Path(path)
    for option, src in inputs:
        if src is None or not str(src).strip():
            continue
        source = Path(src)
        same = target.resolve() == source.resolve()
        if not same and target.exists() and source.exists():
            try:
                same = os.path.samefile(target, source)
            except OSError:
                same = False
        if same:
            raise InputError(f"{path} is also the input {option} ({src}): the output would replace it "
                             "(choose another output name)", field=field)


def _writable(path: Path) -> bool:
    """Writable by this process, and not marked read-only (also when running as root, who may write anyway)."""
    return os.access(path, os.W_OK) and bool(path.stat().st_mode & 0o222)
