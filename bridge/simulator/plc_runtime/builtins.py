"""Operators and library functions of TwinCAT 3 the interpreter implements, and the Python helpers the
generated code calls (memory access, traps, CRCs).

Each entry of :data:`BUILTINS` names the Beckhoff document it follows:

- IEC operators (Infosys "TwinCAT 3 PLC > Reference Programming > Operators"): ADR, SIZEOF, ABS,
  SQRT, LN, LOG, EXP, EXPT, SIN, COS, TAN, ASIN, ACOS, ATAN, MIN, MAX, LIMIT, SEL, MUX, TRUNC,
  TRUNC_INT, the type conversions ``<T1>_TO_<T2>`` and ``TO_<T>``;
- Tc2_System: MEMCPY, MEMSET, MEMMOVE, MEMCMP;
- Tc2_Utilities: F_DATA_TO_CRC16_CCITT (CRC-16/CCITT, polynomial 16#1021, the start value given by
  the caller, no reflection, no final XOR). Tc2_Utilities has no CRC-32 (its CRC functions are
  F_BYTE_TO_CRC16_CCITT and F_DATA_TO_CRC16_CCITT, besides F_CheckSum16): a CRC-32 is written in
  the project's own ST and runs like any other POU;
- hooks that stand for the hardware (not TwinCAT symbols; the allow-list must not list them for
  the project's own POUs, only the library written in ``library.st`` calls them): F_SimTime,
  F_SimAxisIdle, F_SimPersistentCycles, F_SimPersistentSave.

Non-standard names (ATAN2) run but are recorded in :attr:`Program.nonstandard`: TwinCAT 3 does not
know them, so a project that uses them does not build.
"""

from __future__ import annotations

import binascii
import math
import struct
import zlib
from dataclasses import dataclass
from typing import Callable

from pmcal.bridge.simulator.plc_runtime.datatypes import ELEMENTARY, DType, elementary


class PlcException(Exception):
    """The task stopped, as TwinCAT stops a task on an FPU or access exception.

    ``kind``: ``"nan"`` (a NaN produced or compared), ``"division"`` (division by zero), ``"domain"``
    (a math function outside its domain), ``"overflow"``, ``"bounds"`` (array index outside its
    bounds), ``"access"`` (a pointer outside PLC memory), ``"conversion"`` (NaN/inf to an integer).
    """

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


@dataclass
class Builtin:
    compile: Callable
    doc: str
    nonstandard: bool = False
    simulation: bool = False
    memory: bool = False                # reads or writes PLC memory through an address


def _real_arg(c, node, pre, check=True):
    from pmcal.bridge.simulator.plc_runtime.compiler import ANYINT, PlcCompileError
    e = c.expr(node, pre)
    if e.t.kind == "real":
        return f"_nan({e.code})" if e.arith and check else e.code
    if e.t is ANYINT or e.t.kind == "int":
        return f"float({e.code})"
    raise PlcCompileError(f"{c.pou.name}: real argument expected, got {e.t.name}")


def _args(positional, named, names):
    out = list(positional)
    for n in names[len(out):]:
        if n.lower() in named:
            out.append(named[n.lower()])
    return out


def _math1(pyfn):
    def comp(c, positional, named, pre):
        from pmcal.bridge.simulator.plc_runtime.compiler import LREAL, E
        (x,) = _args(positional, named, ["IN"])
        c.math_calls += 1
        # no NaN check of the argument: a NaN argument gives a NaN result, checked where it goes
        return E(f"{pyfn}({_real_arg(c, x, pre, check=False)})", LREAL, arith=True)
    return comp


def _math2(pyfn):
    def comp(c, positional, named, pre):
        from pmcal.bridge.simulator.plc_runtime.compiler import LREAL, E
        a, b = _args(positional, named, ["IN1", "IN2"])
        c.math_calls += 1
        return E(f"{pyfn}({_real_arg(c, a, pre)}, {_real_arg(c, b, pre)})", LREAL, arith=True)
    return comp


def _abs(c, positional, named, pre):
    from pmcal.bridge.simulator.plc_runtime.compiler import E
    (x,) = _args(positional, named, ["IN"])
    e = c.expr(x, pre)
    if e.t.kind == "real":
        return E(f"abs({e.code})", e.t, arith=e.arith)
    return E(f"abs({e.code})", e.t)


def _minmax(fn):
    def comp(c, positional, named, pre):
        from pmcal.bridge.simulator.plc_runtime.compiler import E, _wider
        es = [c.expr(x, pre) for x in positional]
        if any(e.t.kind == "real" for e in es):
            t = next(e.t for e in es if e.t.kind == "real")
            return E(f"_{fn}r({', '.join(e.code for e in es)})", t, arith=any(e.arith for e in es))
        t = es[0].t
        for e in es[1:]:
            t = _wider(t, e.t)
        return E(f"{fn}({', '.join(e.code for e in es)})", t)
    return comp


def _limit(c, positional, named, pre):
    from pmcal.bridge.simulator.plc_runtime.compiler import E, _wider
    mn, x, mx = [c.expr(a, pre) for a in _args(positional, named, ["MN", "IN", "MX"])]
    if any(e.t.kind == "real" for e in (mn, x, mx)):
        return E(f"_minr(_maxr({x.code}, {mn.code}), {mx.code})", x.t, arith=x.arith)
    return E(f"min(max({x.code}, {mn.code}), {mx.code})", _wider(x.t, _wider(mn.t, mx.t)))


def _sel(c, positional, named, pre):
    from pmcal.bridge.simulator.plc_runtime.compiler import E
    g, a, b = [c.expr(x, pre) for x in _args(positional, named, ["G", "IN0", "IN1"])]
    return E(f"({b.code} if {g.code} else {a.code})", a.t, arith=a.arith or b.arith)


def _mux(c, positional, named, pre):
    from pmcal.bridge.simulator.plc_runtime.compiler import E
    k, *ins = [c.expr(x, pre) for x in positional]
    return E(f"({', '.join(e.code for e in ins)},)[_ix({k.code}, 0, {len(ins) - 1})]", ins[0].t,
             arith=any(e.arith for e in ins))


def _trunc(tname):
    def comp(c, positional, named, pre):
        from pmcal.bridge.simulator.plc_runtime.compiler import E
        (x,) = _args(positional, named, ["IN"])
        t = elementary(tname)
        return E(t.wrap_code(f"_toint({_real_arg(c, x, pre)})"), t)
    return comp


def _shift(kind):
    """SHL/SHR/ROL/ROR on the bit width of IN's type (Infosys TC3 PLC, Bit-shift operators)."""
    def comp(c, positional, named, pre):
        from pmcal.bridge.simulator.plc_runtime.compiler import ANYINT, PlcCompileError, E
        x, n = [c.expr(a, pre) for a in _args(positional, named, ["IN", "N"])]
        t = x.t if x.t is not ANYINT else elementary("DWORD")
        if t.kind not in ("int", "enum"):
            raise PlcCompileError(f"{c.pou.name}: {kind} of {t.name}")
        bits, mask = t.bits, (1 << t.bits) - 1
        v = f"(({x.code}) & {mask:#x})"
        if kind == "SHL":
            code = f"(({v} << {n.code}) & {mask:#x})"
        elif kind == "SHR":
            code = f"({v} >> {n.code})"
        elif kind == "ROL":
            code = f"((({v} << ({n.code} % {bits})) | ({v} >> (({bits} - {n.code} % {bits}) % {bits}))) & {mask:#x})"
        else:
            code = f"((({v} >> ({n.code} % {bits})) | ({v} << (({bits} - {n.code} % {bits}) % {bits}))) & {mask:#x})"
        return E(code, t)
    return comp


def _adr(c, positional, named, pre):
    from pmcal.bridge.simulator.plc_runtime.compiler import POINTER, E
    (x,) = positional or list(named.values())
    return E(c.address_of(x, pre), POINTER)


def _sizeof(c, positional, named, pre):
    from pmcal.bridge.simulator.plc_runtime.compiler import E
    (x,) = positional or list(named.values())
    if type(x).__name__ == "SimpleVariable" and c.lookup(str(x.name)) and c.lookup(str(x.name))[0] == "type":
        size = c.lookup(str(x.name))[1].size
    elif type(x).__name__ == "SimpleVariable" and str(x.name).upper() in ELEMENTARY:
        size = elementary(str(x.name).upper()).size
    else:
        size = c.lvalue(x, []).t.size
    # the type of the result follows the size (Infosys tc3_plc_intro, SIZEOF): USINT below 256, UINT
    # below 65536, UDINT below 2^32, else ULINT
    t = elementary("USINT" if size < 256 else "UINT" if size < 65536 else "UDINT" if size < 2 ** 32 else "ULINT")
    return E(str(size), t, const=size)


def _call(pyname, names, ret, mathy=False, sim=False):
    """A library function called with its inputs in ``names`` order (named or positional)."""
    def comp(c, positional, named, pre):
        from pmcal.bridge.simulator.plc_runtime.compiler import PlcCompileError, E
        vals = _args(positional, named, names)
        if len(vals) != len(names):
            raise PlcCompileError(f"{c.pou.name}: {pyname} needs {', '.join(names)}")
        codes = []
        for v in vals:
            e = c.expr(v, pre)
            codes.append(f"_nan({e.code})" if e.arith else e.code)
        t = elementary(ret) if ret else None
        code = f"{pyname}({', '.join(codes)})"
        if t is None:
            pre.append(code)
            return E("None", elementary("BOOL"))
        return E(code, t, arith=mathy)
    return comp


#: the one-argument numeric operators and the Python function each runs
MATH1 = {"SQRT": "math.sqrt", "SIN": "math.sin", "COS": "math.cos", "TAN": "math.tan", "ASIN": "math.asin",
         "ACOS": "math.acos", "ATAN": "math.atan", "EXP": "_exp", "LN": "_ln", "LOG": "_log10"}

BUILTINS: dict[str, Builtin] = {
    "ADR": Builtin(_adr, "Infosys TC3 PLC, Operators: ADR", memory=True),
    "SIZEOF": Builtin(_sizeof, "Infosys TC3 PLC, Operators: SIZEOF"),
    "ABS": Builtin(_abs, "Infosys TC3 PLC, Numeric operators: ABS"),
    **{name: Builtin(_math1(fn), f"Infosys TC3 PLC, Numeric operators: {name}") for name, fn in MATH1.items()},
    "EXPT": Builtin(_math2("_expt"), "Infosys TC3 PLC, Numeric operators: EXPT"),
    "ATAN2": Builtin(_math2("_atan2"), "not a TwinCAT 3 operator (Numeric operators lists ATAN only)",
                     nonstandard=True),
    "MIN": Builtin(_minmax("min"), "Infosys TC3 PLC, Selection operators: MIN"),
    "MAX": Builtin(_minmax("max"), "Infosys TC3 PLC, Selection operators: MAX"),
    "LIMIT": Builtin(_limit, "Infosys TC3 PLC, Selection operators: LIMIT"),
    "SEL": Builtin(_sel, "Infosys TC3 PLC, Selection operators: SEL"),
    "MUX": Builtin(_mux, "Infosys TC3 PLC, Selection operators: MUX"),
    "TRUNC": Builtin(_trunc("DINT"), "Infosys TC3 PLC, Type conversion operators: TRUNC (to DINT)"),
    "TRUNC_INT": Builtin(_trunc("INT"), "Infosys TC3 PLC, Type conversion operators: TRUNC_INT"),
    "SHL": Builtin(_shift("SHL"), "Infosys TC3 PLC, Bit-shift operators: SHL"),
    "SHR": Builtin(_shift("SHR"), "Infosys TC3 PLC, Bit-shift operators: SHR"),
    "ROL": Builtin(_shift("ROL"), "Infosys TC3 PLC, Bit-shift operators: ROL"),
    "ROR": Builtin(_shift("ROR"), "Infosys TC3 PLC, Bit-shift operators: ROR"),
    "MEMCPY": Builtin(_call("_memcpy", ["destAddr", "srcAddr", "n"], "UDINT"), "Tc2_System: MEMCPY", memory=True),
    "MEMMOVE": Builtin(_call("_memcpy", ["destAddr", "srcAddr", "n"], "UDINT"), "Tc2_System: MEMMOVE", memory=True),
    "MEMSET": Builtin(_call("_memset", ["destAddr", "fillByte", "n"], "UDINT"), "Tc2_System: MEMSET", memory=True),
    "MEMCMP": Builtin(_call("_memcmp", ["pBuf1", "pBuf2", "n"], "DINT"), "Tc2_System: MEMCMP", memory=True),
    "F_DATA_TO_CRC16_CCITT": Builtin(_call("_crc16", ["pData", "cbData", "crc"], "WORD"),
                                     "Tc2_Utilities: F_DATA_TO_CRC16_CCITT", memory=True),
    "F_SIMTIME": Builtin(_call("_sim_time", [], "TIME"), "simulation hook: the task clock (ms)", simulation=True),
    "F_SIMAXISIDLE": Builtin(_call("_sim_axis_idle", [], "BOOL"), "simulation hook: axes stand still",
                             simulation=True),
    "F_SIMPERSISTENTCYCLES": Builtin(_call("_sim_persistent_cycles", [], "UDINT"),
                                     "simulation hook: cycles a persistent write takes", simulation=True),
    "F_SIMPERSISTENTSAVE": Builtin(_call("_sim_persistent_save", [], None),
                                   "simulation hook: persistent data saved now", simulation=True),
    "F_SIMCYCLE": Builtin(_call("_sim_cycle", [], "UDINT"), "simulation hook: task cycles completed",
                          simulation=True),
    "F_SIMNCLAG": Builtin(_call("_sim_nc_lag", [], "UDINT"),
                          "simulation hook: task cycles until NcToPlc shows a started move", simulation=True),
    "F_SIMMOVECYCLES": Builtin(_call("_sim_move_cycles", [], "UDINT"),
                               "simulation hook: task cycles a modelled move lasts", simulation=True),
    "F_SIMADSPORT": Builtin(_call("_sim_ads_port", [], "UINT"), "simulation hook: this runtime's AMS port",
                            simulation=True),
    "F_SIMPORTEXISTS": Builtin(_call("_sim_port_exists", ["nPort"], "BOOL"),
                               "simulation hook: a PLC runtime listens on this AMS port", simulation=True),
}


def conversion(c, name: str, positional, pre):
    """``<SRC>_TO_<DST>`` and ``TO_<DST>``: integers wrap, reals round to nearest-even into integers
    (TRUNC truncates), LREAL_TO_REAL rounds to single precision; NaN/inf into an integer stop the task."""
    from pmcal.bridge.simulator.plc_runtime.compiler import ANYINT, PlcCompileError, E
    up = name.upper()
    dst_name = up.split("TO_")[-1]
    if dst_name not in ELEMENTARY and dst_name not in ("BOOL",):
        raise PlcCompileError(f"{c.pou.name}: unknown conversion {name}")
    dst = elementary(dst_name)
    (x,) = positional
    e = c.expr(x, pre)
    src = e.t
    if dst.kind == "real":
        if src.kind == "real":
            code = f"_nan({e.code})" if e.arith else e.code
            return E(f"_f32({code})" if dst.name == "REAL" else code, dst)
        if src.kind == "bool":
            return E(f"(1.0 if {e.code} else 0.0)", dst)
        return E(f"float({e.code})", dst)
    if dst.kind == "bool":
        return E(f"({e.code} != 0)", dst)
    if src.kind == "real":
        code = f"_nan({e.code})" if e.arith else e.code
        return E(dst.wrap_code(f"_round({code})"), dst)
    if src.kind == "bool":
        return E(f"(1 if {e.code} else 0)", dst)
    if src is ANYINT or src.kind in ("int", "enum", "pointer"):
        return E(dst.wrap_code(e.code), dst)
    raise PlcCompileError(f"{c.pou.name}: {name} of {src.name}")


# ====================================================================== run-time helpers
def crc16_ccitt(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT as Tc2_Utilities F_DATA_TO_CRC16_CCITT: polynomial 16#1021, MSB first, start value
    ``crc`` (16#FFFF for CRC-16/CCITT-FALSE, check value 16#29B1 for '123456789'), no final XOR."""
    return binascii.crc_hqx(data, crc)


def crc32_ieee(data: bytes, crc: int = 0) -> int:
    """CRC-32 (IEEE 802.3, reflected polynomial 16#EDB88320, start/final XOR 16#FFFFFFFF; check value
    16#CBF43926 for '123456789'), chained: ``crc`` is the previous result (0 to start)."""
    return zlib.crc32(data, crc) & 0xFFFFFFFF


def namespace_for_constants() -> dict:
    """Names available when folding constant expressions at compile time."""
    return {"_idiv": _idiv, "_imod": _imod, "_expt": math.pow, "math": math}


def _idiv(a: int, b: int) -> int:
    if b == 0:
        raise ZeroDivisionError("integer division by zero")
    q = abs(a) // abs(b)
    return q if (a >= 0) == (b >= 0) else -q


def _imod(a: int, b: int) -> int:
    if b == 0:
        raise ZeroDivisionError("MOD by zero")
    return a - _idiv(a, b) * b


def make_helpers(rt) -> dict:
    """The helper functions of one runtime (they close over its memory and counters)."""
    mem = rt.mem
    work = rt.work_now
    size = len(mem)
    nan_kind = PlcException

    def trap(kind, msg):
        raise nan_kind(kind, msg)

    def _nan(x):
        if x != x:
            trap("nan", "invalid floating-point operation: NaN produced")
        return x

    def _nanerr():
        trap("nan", "invalid floating-point operation: NaN produced")

    def _cmp_false(a, b):
        if a != a or b != b:
            trap("nan", "comparison with a NaN operand")
        return False

    def _cmp_ne(a, b):
        if a != a or b != b:
            trap("nan", "comparison with a NaN operand")
        return True

    def _cmp_nan(a, b):
        if a != a or b != b:
            trap("nan", "comparison with a NaN operand")

    def _eq(a, b):
        r = a == b
        if not r:
            _cmp_nan(a, b)
        return r

    def _ne(a, b):
        r = a != b
        if r:
            _cmp_nan(a, b)
        return r

    def _lt(a, b):
        r = a < b
        if not r:
            _cmp_nan(a, b)
        return r

    def _gt(a, b):
        r = a > b
        if not r:
            _cmp_nan(a, b)
        return r

    def _le(a, b):
        r = a <= b
        if not r:
            _cmp_nan(a, b)
        return r

    def _ge(a, b):
        r = a >= b
        if not r:
            _cmp_nan(a, b)
        return r

    def _minr(*xs):
        for x in xs:
            if x != x:
                trap("nan", "MIN/MAX of a NaN operand")
        return min(xs)

    def _maxr(*xs):
        for x in xs:
            if x != x:
                trap("nan", "MIN/MAX of a NaN operand")
        return max(xs)

    def _ix(i, lo, hi):
        if lo <= i <= hi:
            return i - lo
        trap("bounds", f"array index {i} outside {lo}..{hi}")

    def _ptr(p):
        if 0 < p < size:
            return p
        trap("access", f"pointer {p:#x} outside PLC memory")

    def _span(a, n, what):
        if n < 0 or a <= 0 or a + n > size:
            trap("access", f"{what}: {n} bytes at {a:#x} outside PLC memory")

    def _memcpy(d, s, n):
        _span(d, n, "MEMCPY destination")
        _span(s, n, "MEMCPY source")
        mem[d:d + n] = mem[s:s + n]
        work[2] += n
        return d

    def _copy(d, s, n):
        mem[d:d + n] = mem[s:s + n]
        work[2] += n

    def _memset(d, fill, n):
        _span(d, n, "MEMSET")
        mem[d:d + n] = bytes([fill & 0xFF]) * n
        work[2] += n
        return d

    def _memcmp(a, b, n):
        _span(a, n, "MEMCMP")
        _span(b, n, "MEMCMP")
        work[2] += n                                   # bytes compared: streamed like a copy
        x, y = bytes(mem[a:a + n]), bytes(mem[b:b + n])
        return 0 if x == y else (-1 if x < y else 1)

    def _crc16(p, n, crc):
        _span(p, n, "F_DATA_TO_CRC16_CCITT")
        work[3] += n
        return rt.library["F_DATA_TO_CRC16_CCITT"](bytes(mem[p:p + n]), crc) & 0xFFFF

    def _strcpy(d, cap, src):
        data = bytes(src)[:cap - 1]
        mem[d:d + len(data)] = data
        mem[d + len(data)] = 0

    def _cstr(a):
        end = mem.find(b"\0", a)
        return bytes(mem[a:end if end >= 0 else a])

    def _toint(x):
        if x != x or x in (math.inf, -math.inf):
            trap("conversion", "NaN or infinity converted to an integer")
        return int(x)

    def _round(x):
        if x != x or x in (math.inf, -math.inf):
            trap("conversion", "NaN or infinity converted to an integer")
        return round(x)

    def _f32(x):
        try:
            return struct.unpack("<f", struct.pack("<f", x))[0]
        except OverflowError:
            return math.copysign(math.inf, x)

    def _exp(x):
        try:
            return math.exp(x)
        except OverflowError:
            return rt.overflow(x)

    def _expt(a, b):
        try:
            return math.pow(a, b)
        except OverflowError:
            return rt.overflow(a)

    def _ln(x):
        return math.log(x)

    def _log10(x):
        return math.log10(x)

    def _atan2(y, x):
        return math.atan2(y, x)

    helpers = {name: fn for name, fn in locals().items() if name.startswith("_") and callable(fn)}
    for fmt in "bBhHiIqQfd":
        s = struct.Struct("<" + fmt)
        helpers[f"_U{fmt}"] = s.unpack_from
        helpers[f"_P{fmt}"] = s.pack_into
        if s.size > 1:
            helpers[f"_M{fmt}"] = memoryview(mem).cast(fmt)     # aligned access (len(mem) % 8 == 0)
    helpers.update(math=math, mem=mem, _W=work, _idiv=_idiv, _imod=_imod,
                   _sim_time=lambda: rt.clock_ms & 0xFFFFFFFF, _sim_axis_idle=lambda: bool(rt.motion_idle),
                   _sim_persistent_cycles=lambda: rt.persistent_write_cycles,
                   _sim_persistent_save=rt.mark_persistent_saved, _sim_ads_port=lambda: rt.ams_port,
                   _sim_cycle=lambda: rt.cycles & 0xFFFFFFFF, _sim_nc_lag=lambda: rt.nc_lag_cycles,
                   _sim_move_cycles=lambda: rt.move_cycles,
                   _sim_port_exists=lambda port: port in rt.ams_ports)
    return helpers
