"""ADS protocol details in one place: where GVL_CompTable lives, its symbols' ADS types, link errors.

Configuration as data: :class:`AdsMap` names the GVL and the AMS port; the symbols (names, PLC types,
sizes) and the write allow-lists come from the GVL declaration in :mod:`pmcal.bridge.plc_types`.
Each symbol is transferred with an explicit ctypes type of exactly the symbol's size
(``ARRAY [0..19999] OF LREAL``, format 4's flat table, as ``c_double * 20000``; structs as their packed
byte image: ST_CompTableHeader 248 bytes, ST_CompTableLookupIn 32, ST_CompTableLookupOut 64), never with
pyads' type guessing (which silently writes nothing for multi-dimensional arrays).
"""

from __future__ import annotations

import ctypes
import re
from dataclasses import dataclass
from importlib import resources

import pyads

from pmcal.bridge.plc_types import HOST_PATTERN, SYMBOL, SYMBOLS, Symbol

#: ADS router TCP port of a TwinCAT system
ADS_TCP_PORT = 48898
#: AMS port of the first TwinCAT 3 PLC runtime
PLC_AMS_PORT = 851

#: ADS/AMS/socket errors after which the link is closed, reopened and the transfer restarted
#: (no route, port not connected, time-out, invalid response, handles invalid after online change)
LINK_ERRORS = frozenset({6, 7, 10, 13, 18, 1809, 1812, 1826, 1861, 1864, 1876})

_SCALAR = {"UINT": ctypes.c_uint16, "UDINT": ctypes.c_uint32}


@dataclass(frozen=True)
class AdsMap:
    """Where the compensation-table interface lives on the PLC."""

    gvl: str = "GVL_CompTable"
    ams_port: int = PLC_AMS_PORT

    def name(self, key: str) -> str:
        """Full ADS symbol name of a GVL variable, e.g. ``GVL_CompTable.aShadow``."""
        return f"{self.gvl}.{SYMBOL[key].st_name}"

    @property
    def symbols(self) -> tuple[Symbol, ...]:
        return SYMBOLS


def read_only_symbols(gvl_text: str | None = None) -> frozenset[str]:
    """ST names of the GVL variables declared ``{attribute 'symbol' := 'read'}`` (or ``'none'``):
    TwinCAT answers an ADS write to them with 0x704 (reading/writing not permitted).

    ``gvl_text``: the .TcGVL source (default: the shipped ``plc/GVLs/GVL_CompTable.TcGVL``).
    """
    if gvl_text is None:
        gvl_text = resources.files("pmcal.plc").joinpath("GVLs/GVL_CompTable.TcGVL").read_text(encoding="utf-8")
    found = re.findall(r"\{attribute\s+'symbol'\s*:=\s*'(read|none)'\}\s*(?:\{[^}]*\}\s*)*(\w+)\s*:",
                       gvl_text, re.I)
    return frozenset(name for _, name in found)


#: sizes of the elementary IEC types, bytes
_ELEMENTARY = {"BOOL": 1, "BYTE": 1, "SINT": 1, "USINT": 1, "WORD": 2, "INT": 2, "UINT": 2, "DWORD": 4, "DINT": 4,
               "UDINT": 4, "REAL": 4, "TIME": 4, "LWORD": 8, "LINT": 8, "ULINT": 8, "LREAL": 8, "LTIME": 8}


def struct_members(type_name: str) -> dict[str, tuple[int, int, str]] | None:
    """Members of a DUT of the shipped PLC sources: lower-case name -> (byte offset, size, type), or None
    if ``type_name`` is not a struct there. Follows ``pack_mode`` and TwinCAT 3's natural alignment
    (Infosys tc3_plc_intro, Alignment, https://infosys.beckhoff.com/content/1033/tc3_plc_intro/3539428491.html),
    nested structs, enums (their base type), ``STRING(n)`` and one-dimensional arrays with literal bounds.
    Nested members come as ``outer.inner``.
    """
    layout = _struct_layout(type_name)
    return None if layout is None else layout[0]


def _struct_layout(type_name: str) -> tuple[dict, int, int] | None:
    """(members, size, alignment) of a struct DUT. A member of alignment a (an elementary type: its size; a
    struct: its largest member's) sits at a multiple of min(a, pack mode) (default 8; 0 and 1: no gaps); the
    struct's alignment is the largest of these and its size a multiple of it (so arrays of it stay
    aligned)."""
    text = _dut_text(type_name)
    if text is None or not re.search(r"\bSTRUCT\b", text):
        return None
    m = re.search(r"'pack_mode'\s*:=\s*'(\d+)'", text)
    pack = max(int(m[1]), 1) if m else 8
    body = re.sub(r"//[^\n]*|\(\*.*?\*\)", "", text.split("STRUCT", 1)[1].rsplit("END_STRUCT", 1)[0], flags=re.S)
    out, offset, struct_align = {}, 0, 1
    for name, st_type in re.findall(r"(\w+)\s*:\s*([^;:=]+?)\s*(?::=[^;]*)?;", body):
        size, align, inner = _type_size(st_type.strip())
        if size is None:
            return None
        align = min(align, pack)
        struct_align = max(struct_align, align)
        offset = -(-offset // align) * align
        out[name.lower()] = (offset, size, st_type.strip())
        for sub, (o, n, t) in (inner or {}).items():
            out[f"{name.lower()}.{sub}"] = (offset + o, n, t)
        offset += size
    return out, -(-offset // struct_align) * struct_align, struct_align


def _type_size(st_type: str) -> tuple[int | None, int, dict | None]:
    """(size, alignment, members) of a member type."""
    upper = st_type.upper()
    if upper in _ELEMENTARY:
        return _ELEMENTARY[upper], _ELEMENTARY[upper], None
    m = re.fullmatch(r"STRING\s*\(\s*(\d+)\s*\)", st_type, re.I)
    if m:
        return int(m[1]) + 1, 1, None
    m = re.fullmatch(r"ARRAY\s*\[\s*(-?\d+)\s*\.\.\s*(-?\d+)\s*\]\s*OF\s+(.+)", st_type, re.I)
    if m:
        size, align, _ = _type_size(m[3].strip())
        return (None if size is None else size * (int(m[2]) - int(m[1]) + 1)), align, None
    layout = _struct_layout(st_type)
    if layout is not None:
        members, size, align = layout
        return size, align, members
    text = _dut_text(st_type)
    if text is not None:                          # an enum: its base type after the closing bracket
        m = re.search(r"\)\s*(\w+)\s*;", text)
        size = _ELEMENTARY.get((m[1] if m else "INT").upper(), 2)
        return size, size, None
    return None, 1, None


def _dut_text(type_name: str) -> str | None:
    path = resources.files("pmcal.plc").joinpath(f"DUTs/{type_name}.TcDUT")
    try:
        return path.read_text(encoding="utf-8")
    except (FileNotFoundError, OSError):
        return None


def ctype_of(sym: Symbol) -> type:
    """The ctypes type that carries ``sym`` exactly (size checked against the declaration)."""
    if sym.st_type in _SCALAR:
        t = _SCALAR[sym.st_type]
    elif sym.st_type.endswith("OF LREAL"):
        t = pyads.PLCTYPE_ARR_LREAL(sym.size // 8)
    else:
        t = ctypes.c_uint8 * sym.size
    assert ctypes.sizeof(t) == sym.size, sym
    return t


@dataclass(frozen=True)
class AdsTarget:
    """An ADS endpoint: AMS NetID, host, ADS router TCP port."""

    netid: str
    host: str
    tcp_port: int = ADS_TCP_PORT

    def __str__(self) -> str:
        return f"{self.netid}@{self.host}:{self.tcp_port}"

    @classmethod
    def parse(cls, text: str) -> "AdsTarget":
        """``NETID@HOST[:PORT]``, e.g. ``5.80.201.232.1.1@192.168.1.10`` (ValueError if malformed)."""
        m = re.fullmatch(rf"((?:\d{{1,3}}\.){{5}}\d{{1,3}})@({HOST_PATTERN})(?::(\d{{1,5}}))?", text.strip())
        if not m or any(int(x) > 255 for x in m[1].split(".")) or (m[3] and not 0 < int(m[3]) < 65536):
            raise ValueError(f"ADS target {text!r}: expected NETID@HOST[:PORT] with a six-byte AMS NetID "
                             "like 5.80.201.232.1.1")
        return cls(m[1], m[2], int(m[3]) if m[3] else ADS_TCP_PORT)
