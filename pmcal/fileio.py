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
#: First line of :data:`MARKER`; the files pmcal wrote into the folder follow, one per line
MARKER_TEXT = "written by pmcal; the whole folder is replaced on the next run. Files written:\n"


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


class _DuplicateKey(Exception):
    """A key given twice in one JSON object (raised by :func:`_unique_keys`, turned into an InputError)."""


def _unique_keys(pairs: list[tuple[str, object]]) -> dict:
    """``object_pairs_hook`` of :func:`read_json`: the object's pairs as a dict, a key given twice refused
    (``json`` would keep the last one without a word)."""
    doc = {}
    for key, value in pairs:
        if key in doc:
            raise _DuplicateKey(key)
        doc[key] = value
    return doc


def read_json(path: str | os.PathLike, field: str | None = None) -> object:
    """The JSON document in ``path`` (a byte-order mark accepted); :class:`InputError` naming the file for a
    missing, unreadable or malformed file (with the line and column of a syntax error) and for a key given
    twice in one object (``FILE: duplicate key 'K'``; the last one would win silently)."""
    text = read_text(path, field=field)
    try:
        return json.loads(text, object_pairs_hook=_unique_keys)
    except _DuplicateKey as exc:
        raise InputError(f"duplicate key '{exc.args[0]}'", file=str(path), field=field) from None
    except json.JSONDecodeError as exc:
        raise InputError(f"not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})", file=str(path),
                         field=field) from None
    except RecursionError:                   # [[[[... : Python's decoder recurses per level
        raise InputError("not a JSON file pmcal wrote: its arrays or objects nest thousands of levels deep",
                         file=str(path), field=field) from None


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
    """Build a directory in a temporary sibling; on success swap it in for ``path``.

    ``path`` is checked first (:func:`check_output` with ``folder=True``: never the working folder or one
    of its parents, an existing folder only if pmcal wrote it or it is empty) and again just before the
    swap. The old folder is never deleted first: it is renamed aside, the new one renamed into its place,
    and only then the old one removed; the marker lists the files written, so the next run knows them.
    """
    target = Path(path)
    _check_not_protected(target, (), None, None)
    target.parent.mkdir(parents=True, exist_ok=True)
    check_output(target, folder=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    old = None
    try:
        yield tmp
        mode = _default_mode()
        os.chmod(tmp, mode | ((mode & 0o444) >> 2))     # directories: x where r is granted
        written = sorted(str(p.relative_to(tmp)) for p in tmp.rglob("*") if p.is_file())
        (tmp / MARKER).write_text(MARKER_TEXT + "".join(f"{name}\n" for name in written), encoding="utf-8")
        check_output(target, folder=True)            # still pmcal's own or empty (nothing changed meanwhile)
        if target.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old.", dir=target.parent))
            os.replace(target, old / "previous")
        os.replace(tmp, target)
    except BaseException:
        if old is not None and (old / "previous").exists() and not target.exists():   # put the previous one back
            os.replace(old / "previous", target)
        shutil.rmtree(tmp, ignore_errors=True)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        raise
    if old is not None:
        try:
            shutil.rmtree(old, ignore_errors=True)
        finally:                                     # a signal during the removal: finish it, then stop
            shutil.rmtree(old, ignore_errors=True)


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


def protected_folders(machine_folder: str | os.PathLike | None = None) -> list[tuple[str, Path]]:
    """(what, resolved folder) that no output may be, contain or (the machine folder) sit inside: the
    working folder and each of its parents, and ``machine_folder`` if given."""
    cwd = Path.cwd().resolve()
    out = [("the working folder", cwd)] + [("a parent of the working folder", p) for p in cwd.parents]
    if machine_folder is not None:
        out.append(("the machine folder", Path(machine_folder).resolve()))
    return out


def check_output(path: str | os.PathLike, *, folder: bool = False, force: bool = False,
                 field: str | None = None, suffixes: tuple[str, ...] = (), inputs=(),
                 machine_folder: str | os.PathLike | None = None, own: str | None = None) -> None:
    """The one output guard: check before any work that ``path`` can be written without losing anything;
    raise :class:`InputError` (one line naming the output) otherwise. Used by every command (through
    ``pmcal.cli``), by :func:`atomic_directory` and by the API's ``save`` methods.

    Whatever ``force`` says, an output may never be, contain, or sit inside one of ``inputs`` ((option,
    path) pairs, also by inode: a hard link, a symlink) or ``machine_folder``, and may never be or contain
    the working folder or one of its parents (:func:`protected_folders`).

    A file output must not be a folder, must not be a read-only file, and its folder must exist and be
    writable; its name must end in one of ``suffixes`` (its format's; any when empty). A file the user
    did not name (a side file such as the table's CSV) is replaced only when it is pmcal's own: ``own``
    is the text such a file starts with. A folder output (``folder=True``) must not be a file; if it
    exists it is replaced only when it is empty or pmcal's own: it holds :data:`MARKER` and nothing but
    the files the marker lists (``force`` does not change this: pmcal never replaces a user's folder).
    """
    if path is None:
        return
    if not str(path).strip():
        raise InputError("empty output path", field=field)
    target = Path(path)
    parent = target.parent if str(target.parent) else Path(".")
    _check_not_protected(target, inputs, machine_folder, field)
    if not parent.is_dir():
        what = "is not a folder" if parent.exists() else "does not exist"
        raise InputError(f"cannot write {target}: the folder {parent} {what}", field=field)
    if not _writable(parent):
        raise InputError(f"cannot write {target}: the folder {parent} is not writable", field=field)
    if folder:
        if target.exists() and not target.is_dir():
            raise InputError(f"{target} is a file, not a folder", field=field)
        foreign = _foreign_entries(target) if target.is_dir() else []
        if foreign:
            raise InputError(f"{target} holds {foreign[0]}{f' and {len(foreign) - 1} more' if len(foreign) > 1 else ''}"
                             f", which pmcal did not write; it would be lost: choose another folder (pmcal replaces "
                             f"only an empty folder or one it wrote, whatever --force says)", field=field)
        return
    if target.is_dir():
        raise InputError(f"{target} is a folder; give a file name", field=field)
    if target.exists() and not _writable(target):
        raise InputError(f"{target} is read-only; it will not be replaced", field=field)
    if suffixes and target.suffix.lower() not in suffixes:
        raise InputError(f"{target}: this output is {' or '.join(s.lstrip('.').upper() for s in suffixes)}; "
                         f"name it with {' or '.join(suffixes)}", field=field)
    if own is not None and target.exists() and not _starts_with(target, own):
        raise InputError(f"{target} would be written beside this output but holds a file pmcal did not write "
                         "there; it would be lost: choose another output name or move that file", field=field)


def _starts_with(path: Path, text: str) -> bool:
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(text.encode("utf-8")) + 3)
    except OSError:
        return False
    return head.removeprefix(b"\xef\xbb\xbf").startswith(text.encode("utf-8"))


def _foreign_entries(folder: Path) -> list[str]:
    """What in an existing output folder pmcal did not write (empty: the folder may be replaced). A
    folder without :data:`MARKER` is wholly foreign unless empty; a marker of an older pmcal, which did
    not list its files, vouches for the whole folder."""
    entries = sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if not p.is_dir())
    marker = folder / MARKER
    if not marker.is_file():
        return entries
    try:
        lines = marker.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError):
        return entries
    if not lines or lines[0] + "\n" != MARKER_TEXT:
        return [] if lines and lines[0].startswith("written by pmcal") else entries
    listed = set(lines[1:]) | {MARKER}
    return [e for e in entries if e not in listed]


def _within(inner: Path, outer: Path) -> bool:
    return inner == outer or outer in inner.parents


def _check_not_protected(target: Path, inputs, machine_folder, field) -> None:
    t = target.resolve()
    for what, folder in protected_folders(machine_folder):
        inside = what == "the machine folder" and _within(t, folder)
        if inside or _within(folder, t):
            rel = "is" if t == folder else "is inside" if inside else "contains"
            raise InputError(f"{target} {rel} {what} ({folder}): writing it could lose your files (choose "
                             "another output; this holds whatever --force says)", field=field)
    for option, src in inputs:
        if src is None or not str(src).strip():
            continue
        source = Path(src)
        s = source.resolve()
        same = t == s
        if not same and target.exists() and source.exists():
            try:
                same = os.path.samefile(target, source)
            except OSError:
                same = False
        if same:
            raise InputError(f"{target} is also the input {option} ({src}): the output would replace it "
                             "(choose another output name)", field=field)
        if _within(s, t) or _within(t, s):
            rel = "contains" if _within(s, t) else "is inside"
            raise InputError(f"{target} {rel} the input {option} ({src}): the output would replace it "
                             "(choose another output)", field=field)


def _writable(path: Path) -> bool:
    """Writable by this process, and not marked read-only (also when running as root, who may write anyway)."""
    return os.access(path, os.W_OK) and bool(path.stat().st_mode & 0o222)
