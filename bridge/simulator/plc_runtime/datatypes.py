"""IEC 61131-3 / TwinCAT 3 data types of the interpreter: sizes, alignment, byte layout.

Layout rules (Beckhoff Infosys, TwinCAT 3 PLC, "Attribute 'pack_mode'" and "Data types"):

- elementary sizes: BOOL, BYTE, SINT, USINT 1; WORD, INT, UINT 2; DWORD, DINT, UDINT, REAL, TIME,
  TOD, DATE, DT 4; LWORD, LINT, ULINT, LREAL, LTIME 8; POINTER and REFERENCE 8 (64-bit runtime);
  STRING(n) n+1 bytes, alignment 1; an enum has the size of its base type (default INT); an enum
  declared ``{attribute 'strict'}`` takes only its own values (Infosys tc3_plc_intro, Attribute 'strict',
  https://infosys.beckhoff.com/content/1033/tc3_plc_intro/3363142027.html: no arithmetic with it, no
  other constant, no value of another type);
- a STRUCT member sits at the next multiple of min(member alignment, pack mode); the struct's size
  is rounded up to min(largest member alignment, pack mode). The default pack mode is 8 (natural
  alignment); ``{attribute 'pack_mode' := '1'}`` packs without gaps;
- a UNION's members all start at 0; its size is the largest member's, rounded to its alignment;
- ARRAY[lo..hi, ...] is row-major (last index fastest), elements back to back; ARRAY OF ARRAY
  nests the same way;
- FUNCTION_BLOCK and PROGRAM instances are laid out like a struct with pack mode 8 (their internals
  are not part of any interface; only GVL symbols and DUTs are read as raw bytes over ADS).

Little-endian throughout (x86/ARM TwinCAT targets).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field


class PlcTypeError(Exception):
    """A declaration the interpreter cannot lay out (unknown type, bad bounds)."""


#: name -> (size, struct format, kind, signed)
ELEMENTARY = {
    "BOOL": (1, "B", "bool", False),
    "BYTE": (1, "B", "int", False), "USINT": (1, "B", "int", False), "SINT": (1, "b", "int", True),
    "WORD": (2, "H", "int", False), "UINT": (2, "H", "int", False), "INT": (2, "h", "int", True),
    "DWORD": (4, "I", "int", False), "UDINT": (4, "I", "int", False), "DINT": (4, "i", "int", True),
    "LWORD": (8, "Q", "int", False), "ULINT": (8, "Q", "int", False), "LINT": (8, "q", "int", True),
    "REAL": (4, "f", "real", False), "LREAL": (8, "d", "real", False),
    "TIME": (4, "I", "int", False), "TOD": (4, "I", "int", False), "TIME_OF_DAY": (4, "I", "int", False),
    "DATE": (4, "I", "int", False), "DT": (4, "I", "int", False), "DATE_AND_TIME": (4, "I", "int", False),
    "LTIME": (8, "Q", "int", False),
}
POINTER_SIZE = 8


@dataclass(eq=False)
class DType:
    """One data type. ``kind``: bool, int, real, enum, string, array, struct, union, fb, pointer, reference."""

    name: str
    kind: str
    size: int = 0
    align: int = 1
    fmt: str = ""                       # struct format of a scalar ('' for aggregates)
    signed: bool = False
    elem: "DType | None" = None         # array element, pointer/reference target, enum base
    dims: tuple = ()                    # array: ((lo, hi), ...)
    members: dict = field(default_factory=dict)   # struct/union/fb: name -> (offset, DType)
    values: dict = field(default_factory=dict)    # enum: name -> int
    pou: object = None                  # fb/program: the compiled POU description
    strict: bool = False                # enum declared {attribute 'strict'}

    @property
    def scalar(self) -> bool:
        return bool(self.fmt)

    @property
    def is_real(self) -> bool:
        return self.kind == "real"

    @property
    def is_int(self) -> bool:
        return self.kind in ("int", "enum", "pointer")

    @property
    def bits(self) -> int:
        return 8 * self.size

    def wrap_code(self, code: str) -> str:
        """Python code that wraps the integer ``code`` to this type's width (two's complement)."""
        mask = (1 << self.bits) - 1
        if self.kind == "enum" and self.elem is not None:
            return self.elem.wrap_code(code)
        if self.signed:
            half = 1 << (self.bits - 1)
            return f"((({code}) + {half}) & {mask:#x}) - {half}"
        return f"(({code}) & {mask:#x})"

    def wrap(self, value: int) -> int:
        mask = (1 << self.bits) - 1
        if self.signed:
            half = 1 << (self.bits - 1)
            return ((value + half) & mask) - half
        return value & mask

    def __repr__(self) -> str:
        return f"DType({self.name})"


def elementary(name: str) -> DType:
    size, fmt, kind, signed = ELEMENTARY[name]
    return DType(name, kind, size, size, fmt, signed)


def string_type(length: int) -> DType:
    return DType(f"STRING({length})", "string", length + 1, 1)


def pointer_type(target: DType, reference: bool = False) -> DType:
    kind = "reference" if reference else "pointer"
    name = ("REFERENCE TO " if reference else "POINTER TO ") + target.name
    return DType(name, kind, POINTER_SIZE, POINTER_SIZE, "Q", False, elem=target)


def array_type(elem: DType, dims: tuple) -> DType:
    n = 1
    for lo, hi in dims:
        if hi < lo:
            raise PlcTypeError(f"array bounds {lo}..{hi}")
        n *= hi - lo + 1
    name = "ARRAY [" + ", ".join(f"{lo}..{hi}" for lo, hi in dims) + f"] OF {elem.name}"
    return DType(name, "array", n * elem.size, elem.align, elem=elem, dims=tuple(dims))


def enum_type(name: str, base: DType, values: dict, strict: bool = False) -> DType:
    return DType(name, "enum", base.size, base.align, base.fmt, base.signed, elem=base, values=dict(values),
                 strict=strict)


def layout(name: str, kind: str, members: list[tuple[str, DType]], pack: int = 8) -> DType:
    """A struct / union / fb type from its members in declaration order. ``pack``: the pack mode; 0 packs
    without gaps as 1 does (Infosys tc3_plc_intro, Attribute 'pack_mode',
    https://infosys.beckhoff.com/content/1033/tc3_plc_intro/2529746059.html: 0 'aligned', no gaps)."""
    pack = max(pack, 1)
    offs, at, align = {}, 0, 1
    for mname, t in members:
        a = min(t.align, pack)
        align = max(align, a)
        if kind == "union":
            offs[mname] = (0, t)
            at = max(at, t.size)
        else:
            at = -(-at // a) * a
            offs[mname] = (at, t)
            at += t.size
    size = -(-at // align) * align
    return DType(name, kind, size, align, members=offs)


def strides(t: DType) -> list[int]:
    """Byte stride of each index of an array type."""
    out, s = [], t.elem.size
    for lo, hi in reversed(t.dims):
        out.append(s)
        s *= hi - lo + 1
    return out[::-1]


def pack_scalar(t: DType, value) -> bytes:
    return struct.pack("<" + t.fmt, value)
