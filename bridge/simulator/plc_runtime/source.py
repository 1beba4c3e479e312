"""Reading TwinCAT 3 sources (.TcPOU, .TcDUT, .TcGVL and plain .st) with blark into one list of items.

blark (https://github.com/klauer/blark) parses the ST inside the XML wrappers; its transformed
dataclasses (``blark.transform``) are what :mod:`pmcal.bridge.simulator.plc_runtime.compiler` reads. A
METHOD written after its FUNCTION_BLOCK (plain .st, or a <Method> element of a .TcPOU) is attached
to that function block; the pragma ``{attribute 'pack_mode' := 'N'}`` is read from the raw text
(blark keeps pragmas out of the tree).
"""

from __future__ import annotations

import hashlib
import os
import pickle
import re
from dataclasses import dataclass, field
from pathlib import Path

from pmcal.errors import InputError

_PACK = re.compile(r"\{\s*attribute\s+'pack_mode'\s*:=\s*'(\d+)'\s*\}", re.I)
_STRICT = re.compile(r"\{\s*attribute\s+'strict'\s*\}", re.I)
_TYPE_NAME = re.compile(r"\bTYPE\s+(\w+)", re.I)
SUFFIXES = (".TcPOU", ".TcDUT", ".TcGVL")


class PlcSourceError(Exception):
    """A source file blark cannot parse, or an item the interpreter does not know how to place."""


@dataclass
class Unit:
    """One POU, DUT or GVL: the blark declaration object, its body, methods and where it came from."""

    name: str
    item: object                       # blark FunctionBlock / Function / Program / DataTypeDeclaration; a GVL: its blocks
    body: object = None                # blark.transform.StatementList or None
    methods: dict = field(default_factory=dict)   # name -> Unit (item: blark Method)
    file: str = ""
    pack: dict = field(default_factory=dict)      # DUT name -> pack mode
    strict: frozenset = frozenset()                # DUT names declared {attribute 'strict'}
    qualified: bool = False                        # GVL with {attribute 'qualified_only'}


#: what a session without the PLC simulator (the ``sim`` extra: blark, the ST parser) is told
SIMULATOR_MISSING = ("the simulated PLC (mock ADS/Modbus servers, pmcal loop) needs pmcal's PLC simulator, "
                     "not installed here: pip install 'pmcal[sim]'")


def _blark():
    """blark's parser: installed with the ``sim`` extra only (a plain install talks to real PLCs, it does not
    simulate one); without it an :class:`~pmcal.errors.InputError` says how to get it."""
    try:
        import blark.parse as bp
    except ImportError:
        raise InputError(SIMULATOR_MISSING) from None
    return bp


def _type_pragmas(text: str) -> tuple[dict, frozenset]:
    """The DUT attributes the interpreter honours, each from the pragmas above its TYPE line: DUT name ->
    pack mode (``{attribute 'pack_mode' := 'N'}``), and the names declared ``{attribute 'strict'}``."""
    packs, strict, pending, pending_strict = {}, set(), None, False
    for line in text.splitlines():
        if m := _PACK.search(line):
            pending = int(m[1])
        pending_strict = pending_strict or _STRICT.search(line) is not None
        if m := _TYPE_NAME.search(line):
            if pending is not None:
                packs[m[1]] = pending
            if pending_strict:
                strict.add(m[1])
            pending, pending_strict = None, False
    return packs, frozenset(strict)


def _collect(results, file: str, raw: str) -> list[Unit]:
    units: list[Unit] = []
    by_name: dict[str, Unit] = {}
    packs, strict = _type_pragmas(raw)
    for res in results:
        if res.exception is not None:
            raise PlcSourceError(f"{file}: {res.exception}")
        code = res.transform()
        ident = str(res.identifier or "")
        for item in code.items:
            kind = type(item).__name__
            if kind == "StatementList":                  # the implementation part of a .TcPOU
                owner, _, method = ident.split("/")[0].partition(".")
                target = by_name[owner.lower()]
                if method:
                    target.methods[method.lower()].body = item
                else:
                    target.body = item
                continue
            if kind == "Method":
                owner = ident.split("/")[0].partition(".")[0] if ident else ""
                parent = by_name.get(owner.lower()) if owner else None
                if parent is None:                        # plain .st: the last function block
                    parent = next((u for u in reversed(units) if type(u.item).__name__ == "FunctionBlock"), None)
                if parent is None:
                    raise PlcSourceError(f"{file}: METHOD {item.name} outside a FUNCTION_BLOCK")
                parent.methods[str(item.name).lower()] = Unit(str(item.name), item, item.body, file=file)
                continue
            if kind == "DataTypeDeclaration":
                decl = item.declaration
                name = str(decl.name)
            elif kind == "GlobalVariableDeclarations":
                # a TcGVL names its GVL; in a plain .st file an unnamed VAR_GLOBAL block belongs to "GVL"
                name = str(item.name or ident.split("/")[0])
                if file.endswith(".st") and name in ("", "None", Path(file).stem):
                    name = "GVL"
            else:
                name = str(item.name)
            if kind == "GlobalVariableDeclarations":           # a GVL: one unit, its VAR_GLOBAL blocks
                if name.lower() in by_name:
                    by_name[name.lower()].item.append(item)
                    continue
                item = [item]
            unit = Unit(name, item, getattr(item, "body", None), file=file, pack=packs, strict=strict,
                        qualified="qualified_only" in raw)
            units.append(unit)
            by_name[name.lower()] = unit
    return units


def parse_files(paths, cache_dir: Path | None = None) -> list[Unit]:
    """Parse TwinCAT files (and plain ``.st`` files) into units, in the order given.

    ``cache_dir``: keep each file's units there, keyed by the SHA-256 of its text and of this module
    (blark needs 0.1-3 s per file).
    """
    units: list[Unit] = []
    me = hashlib.sha256(Path(__file__).read_bytes()).hexdigest()[:12]
    for path in paths:
        path = Path(path)
        raw = path.read_text(encoding="utf-8")
        cached = None
        if cache_dir is not None:
            key = hashlib.sha256((me + path.name + raw).encode()).hexdigest()[:24]
            cached = Path(cache_dir) / f"unit-{key}.pickle"
            if cached.exists():
                try:
                    units += pickle.loads(cached.read_bytes())
                    continue
                except Exception:    # a stale cache file: parse again
                    pass
        bp = _blark()
        if path.suffix == ".st":
            results = [bp.parse_source_code(raw, fn=str(path))]
        else:
            results = list(bp.parse(path))
        got = _collect(results, path.name, raw)
        if cached is not None:
            try:
                tmp = cached.with_suffix(f".{os.getpid()}.tmp")
                tmp.write_bytes(pickle.dumps(got))
                tmp.replace(cached)
            except Exception:        # unpicklable or unwritable: no cache, same result
                pass
        units += got
    return units


def project_files(folder: Path) -> list[Path]:
    """The TwinCAT source files of a PLC project folder, DUTs and GVLs first (sorted within)."""
    files = [p for p in Path(folder).rglob("*") if p.suffix in SUFFIXES]
    order = {".TcDUT": 0, ".TcGVL": 1, ".TcPOU": 2}
    return sorted(files, key=lambda p: (order[p.suffix], str(p)))
