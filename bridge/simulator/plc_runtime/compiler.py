"""Compile parsed TwinCAT ST (blark dataclasses) into Python source: one function per POU body and method.

The generated module runs against one ``bytearray`` (``mem``) that holds every variable with a memory
address: GVL variables, PROGRAM and FUNCTION_BLOCK instances (each FB body is ``def FB__body(this)``
with ``this`` the instance's address), and static frames of functions/methods for their locals that
need memory (aggregates, or a scalar whose address is taken). Scalar locals of functions and
methods whose address is never taken are Python locals (they are temporary in TwinCAT too). Values
in Python: int (integers, enums, TIME in ms, addresses), float (REAL/LREAL), bool.

Semantics (see the package docstring for sources): integers are computed exactly and wrapped to
the destination type when stored (and by every conversion); a real result of arithmetic that is NaN
stops the task at the point it is stored or passed on, as does an ordered or equality comparison
with a NaN operand; division by zero (integer or real) stops the task (Python's ZeroDivisionError,
mapped by the runtime); math domain errors (SQRT of a negative number, ACOS(2), LN(0)) stop it too.
"""

from __future__ import annotations

import ast
import math
from dataclasses import dataclass, field

from pmcal.bridge.simulator.plc_runtime.cost_model import COSTS
from pmcal.bridge.simulator.plc_runtime.datatypes import (ELEMENTARY, DType, PlcTypeError, array_type, elementary,
                                                enum_type, layout, pointer_type, string_type, strides)
from pmcal.bridge.simulator.plc_runtime.source import PlcSourceError, Unit


class PlcCompileError(PlcSourceError):
    """ST the interpreter does not support (named with its POU and line)."""


_NOCONST = object()
LREAL = elementary("LREAL")
REAL = elementary("REAL")
BOOL = elementary("BOOL")
DINT = elementary("DINT")
LINT = elementary("LINT")
UDINT = elementary("UDINT")
TIME = elementary("TIME")
#: bytes of the %M area at least (the TF6250 default map covers registers 16#3000..16#5FFF = 24 KB of %MB)
M_AREA_MIN = 65536
#: an integer literal: takes the type of the other operand
ANYINT = DType("ANY_INT", "int", 8, 8, "q", True)
POINTER = pointer_type(elementary("BYTE"))



@dataclass
class E:
    """A compiled expression: Python code, its type, whether it is a real arithmetic result (may be
    NaN: checked where it is stored or passed on), and its value if it is a compile-time constant."""

    code: str
    t: DType
    arith: bool = False
    const: object = _NOCONST


@dataclass
class LV:
    """A place that holds a value: a Python local, or memory at an address (code, or constant)."""

    t: DType
    local: str | None = None
    addr: str | None = None
    ref: bool = False                   # a REFERENCE variable: reading/writing goes to its target
    align: int = 0                      # guaranteed alignment of the address (0: derive from addr)

    def __post_init__(self) -> None:
        if self.align == 0:
            self.align = _addr_align(self.addr)

    def read(self) -> str:
        if self.local is not None:
            return self.local
        return load_code(self.t, self.addr, self.align)

    def write(self, value: str) -> str:
        if self.local is not None:
            return f"{self.local} = {value}"
        return store_code(self.t, self.addr, value, self.align)


_SHIFT = {2: 1, 4: 2, 8: 3}


def lowbit(n: int) -> int:
    """Largest power of two (at most 8) dividing ``n``."""
    return 8 if n % 8 == 0 else n & -n


def _addr_align(addr: str | None) -> int:
    """Alignment of an address expression: a constant, or ``this`` (+ constant); FB and PROGRAM
    instances start on 8-byte boundaries (their layout is pack mode 8 and sizes are multiples of 8)."""
    if addr is None:
        return 1
    if addr.isdigit():
        return lowbit(int(addr))
    if addr == "this":
        return 8
    if addr.startswith("this + ") and addr[7:].isdigit():
        return lowbit(int(addr[7:]))
    return 1


def load_code(t: DType, addr: str, align: int = 1) -> str:
    if t.kind == "bool":
        return f"(mem[{addr}] != 0)"
    if t.fmt == "B":
        return f"mem[{addr}]"
    if t.fmt != "f" and t.size > 1 and align >= t.size:
        # an aligned scalar: a typed view of the memory (no struct call)
        return f"_M{t.fmt}[({addr}) >> {_SHIFT[t.size]}]"
    return f"_U{t.fmt}(mem, {addr})[0]"


def store_code(t: DType, addr: str, value: str, align: int = 1) -> str:
    if t.kind == "bool":
        return f"mem[{addr}] = 1 if {value} else 0"
    if t.fmt == "B":
        return f"mem[{addr}] = {value}"
    if t.fmt == "f":
        return f"_P{t.fmt}(mem, {addr}, _f32({value}))"
    if t.size > 1 and align >= t.size:
        return f"_M{t.fmt}[({addr}) >> {_SHIFT[t.size]}] = {value}"
    return f"_P{t.fmt}(mem, {addr}, {value})"


def addr_add(base: str, off: int) -> str:
    if off == 0:
        return base
    if base.isdigit():
        return str(int(base) + off)
    return f"{base} + {off}"


@dataclass
class Var:
    name: str
    t: DType
    block: str                            # VAR_INPUT, VAR_OUTPUT, VAR_IN_OUT, VAR, VAR_TEMP, VAR_STAT, VAR_INST
    init: object = None                   # blark expression / initialisation or None
    location: str | None = None           # AT %MBn
    offset: int = -1                      # in the instance / frame
    local: str | None = None              # python local name (functions and methods)


@dataclass
class Pou:
    name: str
    kind: str                             # function, fb, program, method
    unit: Unit
    vars: dict = field(default_factory=dict)       # lower name -> Var
    order: list = field(default_factory=list)      # Vars in declaration order
    ret: DType | None = None
    methods: dict = field(default_factory=dict)    # lower name -> Pou
    parent: "Pou | None" = None
    itype: DType | None = None            # fb/program: instance layout; function/method: frame layout
    frame_addr: int = -1                  # function/method: static frame address
    index: int = 0                        # slot in the call counters
    pyname: str = ""

    @property
    def params(self) -> list[Var]:
        return [v for v in self.order if v.block in ("VAR_INPUT", "VAR_IN_OUT", "VAR_OUTPUT")]


@dataclass
class GlobalVar:
    gvl: str
    name: str
    t: DType
    addr: int
    persistent: bool
    constant: bool
    hidden: bool = False          # no ADS symbol ({attribute 'hide'}, 'TcNoSymbol'): not remanent either
    retain: bool = False


class Program:
    """Everything the runtime needs: types, layout, the initial memory image and the generated code."""

    def __init__(self) -> None:
        self.types: dict[str, DType] = {}
        self.pous: dict[str, Pou] = {}
        self.gvls: dict[str, dict[str, GlobalVar]] = {}     # lower gvl -> lower name -> GlobalVar
        self.qualified: set[str] = set()
        self.constants: dict[str, tuple] = {}                # "gvl.name" (lower) -> (value, DType, pyname)
        self.instances: dict[str, int] = {}                  # lower program name -> address
        self.size = 0
        self.persistent = (0, 0)                              # PERSISTENT variables: address range
        self.retain = (0, 0)                                  # RETAIN variables: address range
        self.m_area = (0, 0)                                  # %M: address, size
        self.image = bytearray()
        self.source = ""
        self.lines: list[tuple[int, str, int]] = []           # (python line, POU, ST line)
        self.nonstandard: dict[str, set] = {}                # call name -> POUs using it
        self.call_names: list[str] = []                       # POU per call-counter slot
        self.pure: set[str] = set()                           # FUNCTIONs evaluated once per input

    # -- name lookups used by the runtime ---------------------------------------------------
    def global_var(self, gvl: str, name: str) -> GlobalVar:
        return self.gvls[gvl.lower()][name.lower()]


#: attribute pragmas after which TwinCAT generates no ADS symbol for a variable (and cannot save it
#: as persistent): Infosys tc3_plc_intro, Attribute 'hide' and Attribute 'TcNoSymbol'
NO_SYMBOL_ATTRIBUTES = frozenset({"hide", "tc_no_symbol", "tcnosymbol"})


#: the library POUs written in ST (Tc2_* models and hardware hooks, not project code): they may reach into
#: the internals of the library FBs they model (AXIS_REF), which project ST may not
LIBRARY_FILE = "library.st"
#: register width of the x64 target: TwinCAT computes every intermediate integer result in it and truncates it
#: to its type only when it is stored (Infosys tc3_plc_intro, Operators, /content/1033/tc3_plc_intro/2528853899.html)
REGISTER_BITS = 64
#: what TwinCAT refuses for an enum declared {attribute 'strict'} (compile errors)
STRICT_RULE = ("strict enum: no arithmetic with it, no other constant, no value of another type "
               "(Infosys tc3_plc_intro, Attribute 'strict', /content/1033/tc3_plc_intro/3363142027.html)")


def _no_symbol(decl) -> bool:
    """The declaration carries an attribute that suppresses its ADS symbol (see NO_SYMBOL_ATTRIBUTES)."""
    meta = getattr(decl, "meta", None)
    pragmas = getattr(meta, "attribute_pragmas", None) or []
    return any(str(a).strip().strip("'").lower() in NO_SYMBOL_ATTRIBUTES for a in pragmas)


def _lit_int(tok) -> int:
    return int(str(tok).replace("_", ""))


def duration_ms(lit) -> int:
    total = 0.0
    for part, scale in (("days", 86400000), ("hours", 3600000), ("minutes", 60000), ("seconds", 1000),
                        ("milliseconds", 1)):
        v = getattr(lit, part, None)
        if v is not None:
            total += float(str(v).replace("_", "")) * scale
    return -int(total) if getattr(lit, "negative", False) else int(total)


class Compiler:
    """Builds a :class:`Program` from units (DUTs, GVLs, POUs; library units first)."""

    def __init__(self, units: list[Unit]) -> None:
        self.units = units
        self.prog = Program()
        self.out: list[str] = []
        self.tmp = 0
        self.math_calls = 0
        self.cost = 0                           # modelled CPU cycles of the code being compiled (cost_model)
        self.last_far = False                   # the last reference's address is computed (index, pointer)
        self.pou: Pou | None = None
        self.loop_depth = 0
        self.pure = False
        self.hoist: dict | None = None         # pointer loads of the statement being compiled
        self.impure_call = False                # the statement calls something that may re-point

    # ================================================================== types
    def build(self) -> Program:
        p = self.prog
        dut_units = [u for u in self.units if type(u.item).__name__ == "DataTypeDeclaration"]
        gvl_units = [u for u in self.units if isinstance(u.item, list)]
        pou_units = [u for u in self.units if type(u.item).__name__ in ("FunctionBlock", "Function", "Program")]
        # constants first (array bounds use them): every VAR_GLOBAL CONSTANT with a literal-ish init
        for u in gvl_units:
            for block in u.item:
                if "CONSTANT" in str(block.attrs or "").upper():
                    for d in block.items:
                        self._declare_constant(u.name, d)
        self._dut_units = {str(u.item.declaration.name).lower(): u for u in dut_units}
        self._pou_units = {u.name.lower(): u for u in pou_units}
        for name in list(self._dut_units):
            self.type_named(name)
        for u in pou_units:
            self._pou(u)
        for pou in list(p.pous.values()):
            if pou.kind in ("fb", "program"):
                self.instance_type(pou)
        self._allocate(gvl_units)
        self._generate()
        return p

    def _declare_constant(self, gvl: str, d) -> None:
        name = str(d.spec.variables[0])
        t = self.type_of_spec(d.init)
        value = self.const_value(d.init.value, t) if d.init.value is not None else _zero(t)
        key = f"{gvl}.{name}".lower()
        self.prog.constants[key] = (value, t, f"K_{gvl}__{name}")

    def type_named(self, name: str) -> DType:
        key = name.lower()
        if key in self.prog.types:
            return self.prog.types[key]
        up = name.upper()
        if up in ELEMENTARY:
            t = elementary(up)
        elif up == "STRING":
            t = string_type(80)
        elif key in self._dut_units:
            t = self._dut(self._dut_units[key])
        elif key in self._pou_units:
            pou = self._pou(self._pou_units[key])
            t = self.instance_type(pou)
        else:
            raise PlcTypeError(f"unknown type {name}")
        self.prog.types[key] = t
        return t

    def _dut(self, u: Unit) -> DType:
        decl = u.item.declaration
        kind = type(decl).__name__
        name = str(decl.name)
        pack = u.pack.get(name, 8)
        if kind == "EnumeratedTypeDeclaration":
            spec = decl.init.spec
            base = elementary(str(spec.type_name).upper()) if spec.type_name else elementary("INT")
            values, nxt = {}, 0
            for v in spec.values or []:
                if v.value is not None:
                    nxt = int(self.const_value(v.value, base))
                values[str(v.name).split(".")[-1].lower()] = nxt
                nxt += 1
            return enum_type(name, base, values, strict=name in u.strict)
        if kind == "StructureTypeDeclaration":
            if decl.extends is not None:
                raise PlcCompileError(f"{name}: EXTENDS is not supported")
            members = []
            for d in decl.declarations:
                t = self.type_of_spec(d.init)
                for v in d.variables:
                    members.append((str(v.variable.name), t))
            t = layout(name, "struct", members, pack)
            t.inits = [(str(v.variable.name), d.init) for d in decl.declarations for v in d.variables
                       if getattr(d.init, "value", None) is not None]
            return t
        if kind == "UnionTypeDeclaration":
            members = [(str(d.name), self.type_of_spec(d.spec)) for d in decl.declarations]
            return layout(name, "union", members, pack)
        if kind == "SimpleTypeDeclaration":
            return self.type_of_spec(decl.init)
        if kind == "ArrayTypeDeclaration":
            return self.type_of_spec(decl.init)
        raise PlcCompileError(f"{name}: {kind} is not supported")

    def type_of_spec(self, init) -> DType:
        """DType of a blark type initialisation / specification (via its ST text)."""
        spec = getattr(init, "spec", init)
        return self.type_of_text(str(spec))

    def type_of_text(self, text: str) -> DType:
        s = text.strip()
        up = s.upper()
        if up.startswith("REFERENCE TO "):
            return pointer_type(self.type_of_text(s[13:]), reference=True)
        if up.startswith("POINTER TO "):
            return pointer_type(self.type_of_text(s[11:]))
        if up.startswith("ARRAY"):
            lb, depth, i = s.index("["), 0, s.index("[")
            for i in range(lb, len(s)):
                depth += {"[": 1, "]": -1}.get(s[i], 0)
                if depth == 0:
                    break
            ranges = _split_top(s[lb + 1:i], ",")
            rest = s[i + 1:].strip()
            if not rest.upper().startswith("OF"):
                raise PlcTypeError(f"bad array type {text}")
            elem = self.type_of_text(rest[2:])
            dims = []
            for r in ranges:
                lo, hi = r.split("..")
                dims.append((self.bound(lo), self.bound(hi)))
            return array_type(elem, tuple(dims))
        if up.startswith("STRING"):
            rest = s[6:].strip()
            if not rest:
                return string_type(80)
            return string_type(self.bound(rest.strip("()[]")))
        if ":=" in s:                      # a type with an initial value: "UINT := 4"
            return self.type_of_text(s.split(":=")[0])
        return self.type_named(s)

    def bound(self, text: str) -> int:
        """An array bound / string length: integer arithmetic over literals and constants."""
        def ev(node):
            if isinstance(node, ast.Expression):
                return ev(node.body)
            if isinstance(node, ast.Constant) and isinstance(node.value, int):
                return node.value
            if isinstance(node, ast.BinOp) and isinstance(node.op, (ast.Add, ast.Sub, ast.Mult, ast.FloorDiv)):
                a, b = ev(node.left), ev(node.right)
                return {ast.Add: a + b, ast.Sub: a - b, ast.Mult: a * b}.get(type(node.op), a // b if b else 0)
            if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
                return -ev(node.operand)
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name):
                key = f"{node.value.id}.{node.attr}".lower()
                if key in self.prog.constants:
                    return int(self.prog.constants[key][0])
            if isinstance(node, ast.Name):
                for key, (value, _, _) in self.prog.constants.items():
                    if key.split(".")[1] == node.id.lower():
                        return int(value)
            raise PlcTypeError(f"array bound {text!r} is not a constant expression")
        return ev(ast.parse(text.strip(), mode="eval"))

    # ================================================================== POUs
    def _pou(self, u: Unit) -> Pou:
        key = u.name.lower()
        if key in self.prog.pous:
            return self.prog.pous[key]
        kind = {"FunctionBlock": "fb", "Function": "function", "Program": "program"}[type(u.item).__name__]
        pou = Pou(u.name, kind, u, pyname=f"P_{u.name}")
        self.prog.pous[key] = pou
        if kind == "fb" and (u.item.extends is not None or u.item.implements is not None):
            raise PlcCompileError(f"{u.name}: EXTENDS/IMPLEMENTS is not supported")
        if kind == "function":
            pou.ret = self.type_of_spec(u.item.return_type) if u.item.return_type is not None else None
        self._vars(pou, u.item.declarations)
        for mname, mu in u.methods.items():
            m = Pou(mu.name, "method", mu, parent=pou, pyname=f"P_{u.name}__{mu.name}")
            rt = mu.item.return_type
            m.ret = self.type_of_text(str(rt)) if rt is not None else None
            self._vars(m, mu.item.declarations)
            pou.methods[mname] = m
        return pou

    def _vars(self, pou: Pou, blocks) -> None:
        for block in blocks or []:
            bname = type(block).__name__
            header = getattr(block, "block_header", "VAR")
            if bname == "FunctionVariableDeclarations":
                header = "VAR"
            attrs = str(getattr(block, "attrs", "") or "").upper()
            if "CONSTANT" in attrs:
                header = "VAR_CONSTANT"
            if header in ("VAR_INST", "VAR_STAT") or "RETAIN" in attrs or "PERSISTENT" in attrs:
                # these keep their value between calls / over restarts: not modelled outside a GVL
                raise PlcCompileError(f"{pou.name}: {header} {attrs.strip()} is not supported (use a GVL)")
            for d in block.items:
                dname = type(d).__name__
                if dname == "LocatedVariableDeclaration":
                    names = [str(d.name.name)]
                    location = str(d.location)
                    init = d.init
                else:
                    names = [str(v.variable.name) if hasattr(v, "variable") else str(v) for v in d.variables]
                    located = [v.location for v in d.variables if getattr(v, "location", None) is not None]
                    location = str(located[0]) if located else None          # name AT %MBn : TYPE
                    init = d.init
                    if dname == "FunctionBlockNameDeclaration":
                        init = d.spec
                t = self.type_of_spec(init) if dname != "FunctionBlockNameDeclaration" else self.type_named(str(d.spec))
                value = getattr(init, "value", None)
                for n in names:
                    v = Var(n, t, header, value, location)
                    if header == "VAR_CONSTANT":
                        self.prog.constants[f"{pou.name}.{n}".lower()] = (
                            self.const_value(value, t), t, f"K_{pou.name}__{n}")
                        v.block = "VAR_CONSTANT"
                    pou.vars[n.lower()] = v
                    pou.order.append(v)

    def instance_type(self, pou: Pou) -> DType:
        """Layout of an FB/PROGRAM instance: its inputs, outputs, in-out pointers, VAR (pack mode 8)."""
        if pou.itype is not None:
            return pou.itype
        members = []
        for v in pou.order:
            if v.block == "VAR_CONSTANT" or v.location is not None:
                continue
            t = pointer_type(v.t, reference=True) if v.block == "VAR_IN_OUT" else v.t
            members.append((v.name, t))
        t = layout(pou.name, "fb" if pou.kind == "fb" else "program", members, 8)
        t.align = 8
        t.size = -(-t.size // 8) * 8
        t.pou = pou
        for v in pou.order:
            if v.name in t.members:
                v.offset = t.members[v.name][0]
        pou.itype = t
        self.prog.types.setdefault(pou.name.lower(), t)
        return t

    # ================================================================== memory
    def _allocate(self, gvl_units) -> None:
        p = self.prog
        at = 64                                     # address 0 stays unused: a NULL pointer faults
        inits = []                                   # (address, DType, blark init or None)

        def place(t: DType) -> int:
            nonlocal at
            at = -(-at // 8) * 8
            a = at
            at += t.size
            return a

        # remanent variables in regions of their own (the runtime saves and restores them as a whole):
        # PERSISTENT (also RETAIN PERSISTENT), then RETAIN. A variable TwinCAT makes no symbol for
        # ({attribute 'hide'}, 'tc_no_symbol'/'TcNoSymbol') is not remanent whatever its block says:
        # "variables declared with the 'hide' or 'hide_all_locals' attribute cannot be saved as
        # persistent" (Infosys tc3_plc_intro, Attribute 'hide', /content/1033/tc3_plc_intro/2529654667.html;
        # the same for 'TcNoSymbol', /3108007179.html): it is placed with the ordinary variables.
        remanent = {"PERSISTENT": [], "RETAIN": []}
        for u in gvl_units:
            gvl = u.name.lower()
            p.gvls.setdefault(gvl, {})
            if u.qualified:
                p.qualified.add(gvl)
            for block in u.item:
                attrs = str(block.attrs or "").upper()
                kind = "PERSISTENT" if "PERSISTENT" in attrs else "RETAIN" if "RETAIN" in attrs else None
                for d in block.items:
                    if kind is not None and not _no_symbol(d):
                        remanent[kind].append((u, d))
                    else:
                        self._global(u.name, d, attrs.replace("PERSISTENT", "").replace("RETAIN", ""),
                                     place, inits)
        for kind in ("PERSISTENT", "RETAIN"):
            at = -(-at // 8) * 8
            start = at
            for u, d in remanent[kind]:
                self._global(u.name, d, kind, place, inits)
            at = -(-at // 8) * 8
            if kind == "PERSISTENT":
                p.persistent = (start, at)
            else:
                p.retain = (start, at)
        for pou in p.pous.values():
            if pou.kind == "program":
                p.instances[pou.name.lower()] = a = place(pou.itype)
                inits.append((a, pou.itype, None))
        # %M area: the located variables of programs (AT %MBn), as TwinCAT's memory image
        m_size = 0
        for pou in p.pous.values():
            for v in pou.order:
                if v.location is not None:
                    off = int("".join(ch for ch in v.location.split("MB")[-1] if ch.isdigit()) or 0)
                    v.offset = off
                    m_size = max(m_size, off + v.t.size)
        m_size = max(m_size, M_AREA_MIN)
        p.m_area = (place(DType("%M", "struct", m_size, 8)), m_size)
        # frames of functions and methods (their locals that need memory)
        for pou in p.pous.values():
            for f in [pou, *pou.methods.values()]:
                if f.kind in ("function", "method"):
                    self._frame(f)
                    f.frame_addr = place(f.itype)
        for i, pou in enumerate(self._all_pous()):
            pou.index = i
            p.call_names.append(pou.name if pou.parent is None else f"{pou.parent.name}.{pou.name}")
        p.size = -(-at // 8) * 8 + 64
        p.image = bytearray(p.size)
        for a, t, init in inits:
            self._init_into(p.image, a, t, init)
        for pou in p.pous.values():
            for v in pou.order:
                if v.location is not None:
                    self._init_into(p.image, p.m_area[0] + v.offset, v.t, v.init)

    def _all_pous(self):
        for pou in self.prog.pous.values():
            yield pou
            yield from pou.methods.values()

    def _global(self, gvl: str, d, attrs: str, place, inits) -> None:
        name = str(d.spec.variables[0])
        t = self.type_of_spec(d.init)
        constant = "CONSTANT" in attrs
        a = place(t)
        gv = GlobalVar(gvl, name, t, a, "PERSISTENT" in attrs, constant, _no_symbol(d), "RETAIN" in attrs)
        self.prog.gvls[gvl.lower()][name.lower()] = gv
        inits.append((a, t, getattr(d.init, "value", None)))

    def _frame(self, f: Pou) -> None:
        """Which locals of a function/method live in memory (aggregates, address taken) and where."""
        addressed = _addressed_names(f.unit.body)
        members = []
        for v in f.order:
            if v.block in ("VAR_CONSTANT", "VAR_IN_OUT"):
                continue
            in_mem = not v.t.scalar or v.t.kind == "reference" or v.name.lower() in addressed
            if in_mem:
                members.append((v.name, v.t))
            else:
                v.local = f"v_{v.name}"
        t = layout(f.name, "struct", members, 8)
        for v in f.order:
            if v.name in t.members and v.local is None:
                v.offset = t.members[v.name][0]
        f.itype = t

    def _init_into(self, image: bytearray, addr: int, t: DType, init) -> None:
        """Write the initial value of a variable of type ``t`` at ``addr`` (recursing into FB/struct defaults)."""
        if init is not None and not _is_init_struct(init):
            value = self.const_value(init, t)
            _poke(image, addr, t, value)
            return
        if t.kind in ("fb", "program"):
            for v in t.pou.order:
                if v.block == "VAR_CONSTANT" or v.location is not None or v.block == "VAR_IN_OUT":
                    continue
                self._init_into(image, addr + v.offset, v.t, v.init)
        elif t.kind == "struct":
            for name, vinit in getattr(t, "inits", []):
                off, mt = t.members[name]
                self._init_into(image, addr + off, mt, vinit.value)
            for name, (off, mt) in t.members.items():
                if mt.kind in ("struct", "fb", "array") and name not in {n for n, _ in getattr(t, "inits", [])}:
                    self._init_into(image, addr + off, mt, None)
        elif t.kind == "array" and t.elem.kind in ("struct", "fb", "array"):
            n = t.size // t.elem.size
            for i in range(n):
                self._init_into(image, addr + i * t.elem.size, t.elem, None)

    def const_value(self, expr, t: DType):
        """Evaluate a constant initialisation expression."""
        if expr is None:
            return _zero(t)
        if type(expr).__name__ == "String" or (hasattr(expr, "value") and isinstance(getattr(expr, "value"), str)
                                                 and str(getattr(expr, "value")).startswith("'")):
            return _st_string(str(expr.value))
        saved = self.pou
        self.pou = None
        try:
            e = self.expr(expr, [])
        finally:
            self.pou = saved
        if e.const is not _NOCONST:
            return e.const
        raise PlcCompileError(f"initial value {expr} is not constant")

    # ================================================================== code generation
    def _generate(self) -> None:
        out = self.out
        out.append("# generated from TwinCAT ST by pmcal.bridge.simulator.plc_runtime.compiler; do not edit")
        for key, (value, t, py) in self.prog.constants.items():
            out.append(f"{py} = {value!r}")
        for pou in list(self._all_pous()):
            self._gen_pou(pou)
        self.prog.source = "\n".join(out) + "\n"

    def _line(self, text: str, indent: int) -> None:
        self.out.append("    " * indent + text)

    def _gen_pou(self, pou: Pou) -> None:
        self.pou = pou
        self.tmp = 0
        body = pou.unit.body
        if pou.kind in ("fb", "program"):
            self._line(f"def {pou.pyname}(this):", 0)
            self._line(f"_CALLS[{pou.index}] += 1", 1)
            self._block(body, 1, ret="return")
            self._line("return", 1)
            return
        params = [v for v in pou.order if v.block in ("VAR_INPUT", "VAR_IN_OUT")]
        args = ", ".join(["this"] * (pou.kind == "method") + [f"a_{v.name}" for v in params])
        def_line = len(self.out)
        # a VAR_IN_OUT argument is an address: the same key may hold other contents on the next call, and
        # the function may write through it, so such a function is never evaluated once per input
        self.pure = (pou.kind == "function" and bool(params)
                     and not any(v.block == "VAR_IN_OUT" for v in pou.order))
        self._line(f"def {pou.pyname}({args}):", 0)
        self._line(f"_CALLS[{pou.index}] += 1", 1)
        fa = pou.frame_addr
        if pou.itype.size:
            self._line(f"mem[{fa}:{fa + pou.itype.size}] = bytes({pou.itype.size})", 1)
        for v in pou.order:
            if v.block == "VAR_CONSTANT":
                continue
            lv = self.var_lv(v)
            if v.block in ("VAR_INPUT", "VAR_IN_OUT"):
                if v.block == "VAR_IN_OUT":
                    continue
                self._line(lv.write(f"a_{v.name}") if lv.local is None else f"{lv.local} = a_{v.name}", 1)
            elif v.local is not None:
                self._line(f"{v.local} = {self._initial_code(v)}", 1)
            elif v.init is not None:
                self._line(lv.write(self._initial_code(v)), 1)
            elif v.t.kind in ("fb", "struct", "array"):
                # nested FB instances / structs with defaults in a frame: copy their default image
                img = bytearray(v.t.size)
                self._init_into(img, 0, v.t, None)
                if any(img):
                    self._line(f"mem[{fa + v.offset}:{fa + v.offset + v.t.size}] = {bytes(img)!r}", 1)
        if pou.ret is not None:
            self._line(f"r_ = {_zero(pou.ret)!r}", 1)
        ret = self._return_code(pou)
        self._block(body, 1, ret=f"return {ret}")
        self._line(f"return {ret}", 1)
        if self.pure:
            self._memoize(pou, def_line, args)
        self.pure = False

    def _memoize(self, pou: Pou, def_line: int, args: str) -> None:
        """A pure FUNCTION (reads only its inputs, locals and constants; calls only pure functions and
        numeric operators) is evaluated once per distinct input: the cache returns its result and
        adds the work the evaluation counted, so counters and results are those of a real call.
        Inputs equal to 0 (+0.0/-0.0 are equal keys) always run."""
        self.prog.pure.add(pou.name.lower())
        impl = f"{pou.pyname}__impl"
        self.out[def_line] = f"def {impl}({args}):"
        memo = f"_MEMO_{pou.name}"
        self._line(f"{memo} = {{}}", 0)
        self._line(f"def {pou.pyname}(*a):", 0)
        self._line("if 0 in a:", 1)
        self._line(f"return {impl}(*a)", 2)
        self._line(f"r = {memo}.get(a)", 1)
        self._line("if r is None:", 1)
        self._line("w0, w1, w4 = _W[0], _W[1], _W[4]", 2)
        self._line(f"v = {impl}(*a)", 2)
        self._line(f"if len({memo}) < 200000:", 2)
        self._line(f"{memo}[a] = (v, _W[0] - w0, _W[1] - w1, _W[4] - w4)", 3)
        self._line("return v", 2)
        self._line(f"_CALLS[{pou.index}] += 1", 1)
        self._line("_W[0] += r[1]", 1)
        self._line("_W[1] += r[2]", 1)
        self._line("_W[4] += r[3]", 1)
        self._line("return r[0]", 1)

    def _return_code(self, pou: Pou) -> str:
        outs = [v for v in pou.order if v.block == "VAR_OUTPUT"]
        vals = (["r_"] if pou.ret is not None else ["None"]) + [self.var_lv(v).read() for v in outs]
        return vals[0] if len(vals) == 1 else "(" + ", ".join(vals) + ")"

    def _initial_code(self, v: Var) -> str:
        if v.init is None:
            return repr(_zero(v.t))
        return repr(self.const_value(v.init, v.t))

    # ---------------------------------------------------------------- statements
    def _block(self, stmts, indent: int, ret: str) -> None:
        items = list(getattr(stmts, "statements", None) or [])
        if not items:
            self._line("pass", indent)
            return
        segments, cur = [], []
        for s in items:
            cur.append(s)
            if _jumps(s):
                segments.append(cur)
                cur = []
        if cur:
            segments.append(cur)
        for seg in segments:
            mark = len(self.out)
            self._line("", indent)                 # placeholder for the work counters
            calls0, cost0 = self.math_calls, self.cost
            static, cost = 0, 0
            for s in seg:
                before, cbefore = self.math_calls, self.cost
                self._stmt(s, indent, ret)
                if type(s).__name__ in ("AssignmentStatement", "FunctionCallStatement", "ReferenceAssignmentStatement",
                                        "SetStatement", "ResetStatement"):
                    static += self.math_calls - before
                    cost += self.cost - cbefore
                else:
                    self.math_calls = before + 0   # compound statements count their own conditions
                    self.cost = cbefore            # ... and charge their own cost where they evaluate it
            self.math_calls, self.cost = calls0, cost0
            counter = f"_W[0] += {len(seg)}" + (f"; _W[1] += {static}" if static else "") + \
                (f"; _W[4] += {cost}" if cost else "")
            self.out[mark] = "    " * indent + counter

    def _loc(self, s, indent: int) -> None:
        meta = getattr(s, "meta", None)
        line = getattr(meta, "line", None) if meta is not None else None
        if line is not None:
            self.prog.lines.append((len(self.out) + 1, self.pou.name if self.pou.parent is None
                                    else f"{self.pou.parent.name}.{self.pou.name}", int(line)))

    def _stmt(self, s, indent: int, ret: str) -> None:
        kind = type(s).__name__
        self._loc(s, indent)
        if kind not in ("AssignmentStatement", "ReferenceAssignmentStatement", "SetStatement", "ResetStatement",
                        "FunctionCallStatement"):
            self._stmt_inner(s, indent, ret)
            return
        mark, tmp, calls, cost = len(self.out), self.tmp, self.math_calls, self.cost
        self.hoist, self.impure_call = {}, False
        try:
            self._stmt_inner(s, indent, ret)
            if self.impure_call and self.hoist:          # compile again without hoisting
                del self.out[mark:]
                self.tmp, self.math_calls, self.hoist, self.cost = tmp, calls, None, cost
                self._stmt_inner(s, indent, ret)
        finally:
            self.hoist, self.impure_call = None, False

    def _stmt_inner(self, s, indent: int, ret: str) -> None:
        kind = type(s).__name__
        pre: list[str] = []
        if kind == "AssignmentStatement":
            e = self.expr(s.expression, pre)
            for target in s.variables:
                self._check_write_access(target)
                lv = self.lvalue(target, pre)
                self._emit(pre, indent)
                pre = []
                self._assign(lv, e, indent)
        elif kind == "ReferenceAssignmentStatement":
            lv = self.lvalue(s.variable, pre, raw_ref=True)
            addr = self.address_of(s.expression, pre)
            self._emit(pre, indent)
            self._line(store_code(lv.t, lv.addr, addr) if lv.local is None else f"{lv.local} = {addr}", indent)
        elif kind in ("SetStatement", "ResetStatement"):
            lv = self.lvalue(s.variable, pre)
            c = self.cond(s.expression, pre)
            self._emit(pre, indent)
            self._line(f"if {c}:", indent)
            self._line(lv.write("True" if kind == "SetStatement" else "False"), indent + 1)
        elif kind == "FunctionCallStatement":
            e = self.call(s, pre, statement=True)
            self._emit(pre, indent)
            if e is not None and e.code not in ("None", ""):
                self._line(e.code, indent)
        elif kind == "IfStatement":
            self._if([(s.if_expression, s.statements)] + [(c.if_expression, c.statements) for c in s.else_ifs],
                     s.else_clause, indent, ret)
        elif kind == "CaseStatement":
            c0 = self.cost
            sel = self.expr(s.expression, pre)
            self._emit(pre, indent)
            self._charge(self.cost - c0 + COSTS["branch"], indent)      # a jump table: one branch
            self.cost = c0
            name = self._tmp()
            self._line(f"{name} = {sel.code}", indent)
            branches = []
            for case in s.cases:
                tests = []
                for m in case.matches:
                    if type(m).__name__ in ("Subrange", "PartialSubrange"):
                        lo, hi = self.expr(m.start, []).code, self.expr(m.stop, []).code
                        tests.append(f"{lo} <= {name} <= {hi}")
                    else:
                        tests.append(f"{name} == {self.expr(m, []).code}")
                branches.append((" or ".join(tests), case.statements))
            first = True
            for test, body in branches:
                self._line(f"{'if' if first else 'elif'} {test}:", indent)
                self._block(body, indent + 1, ret)
                first = False
            if s.else_clause is not None:
                self._line("else:" if not first else "if True:", indent)
                self._block(s.else_clause.statements, indent + 1, ret)
        elif kind == "ForStatement":
            c0 = self.cost
            ctl = self.lvalue(s.control, pre)
            start = self.expr(s.from_, pre)
            self._emit(pre, indent)
            self._assign(ctl, start, indent)
            step = self.expr(s.step, []) if s.step is not None else E("1", ANYINT, const=1)
            if step.const is _NOCONST or step.const == 0:
                raise PlcCompileError(f"{self.pou.name}: FOR needs a constant, non-zero BY")
            self._charge(self.cost - c0, indent)
            self.cost = c0
            self._line("while True:", indent)
            pre = []
            end = self.expr(s.to, pre)
            self._emit(pre, indent + 1)
            # per iteration: the bound, the test, the predicted back edge, the increment (load, add, store)
            self._charge(self.cost - c0 + 2 * COSTS["load"] + 2 * COSTS["alu"] + COSTS["loop"] + COSTS["store"],
                         indent + 1)
            self.cost = c0
            op = "<=" if step.const > 0 else ">="
            self._line(f"if not ({ctl.read()} {op} {end.code}):", indent + 1)
            self._charge(COSTS["branch"], indent + 2)
            self._line("break", indent + 2)
            self.loop_depth += 1
            self._block(s.statements, indent + 1, ret)
            self.loop_depth -= 1
            self._line(ctl.write(ctl.t.wrap_code(f"{ctl.read()} + {step.const}")), indent + 1)
        elif kind == "WhileStatement":
            self._line("while True:", indent)
            self._loop_exit(s.expression, pre, indent + 1, when_true=False)
            self.loop_depth += 1
            self._block(s.statements, indent + 1, ret)
            self.loop_depth -= 1
        elif kind == "RepeatStatement":
            self._line("while True:", indent)
            self.loop_depth += 1
            self._block(s.statements, indent + 1, ret)
            self.loop_depth -= 1
            self._loop_exit(s.expression, pre, indent + 1, when_true=True)
        elif kind == "ReturnStatement":
            self._line(ret, indent)
        elif kind == "ExitStatement":
            if not self.loop_depth:
                raise PlcCompileError(f"{self.pou.name}: EXIT outside a loop")
            self._line("break", indent)
        elif kind == "NoOpStatement":
            self._line("pass", indent)
        else:
            raise PlcCompileError(f"{self.pou.name}: {kind} is not supported")

    def _if(self, branches, else_clause, indent: int, ret: str) -> None:
        (expr, body), rest = branches[0], branches[1:]
        self._loc(expr, indent)                    # a trap in an ELSIF condition names its line
        pre: list[str] = []
        c0 = self.cost
        c = self.cond(expr, pre)
        self._emit(pre, indent)
        self._charge(self.cost - c0 + COSTS["branch"], indent)
        self.cost = c0
        self._line(f"if {c}:", indent)
        self._block(body, indent + 1, ret)
        if rest or else_clause is not None:
            self._line("else:", indent)
            if rest:
                self._if(rest, else_clause, indent + 1, ret)
            else:
                self._block(else_clause.statements, indent + 1, ret)

    def _loop_exit(self, expression, pre: list, indent: int, when_true: bool) -> None:
        """A loop's test (WHILE: leave when false; REPEAT ... UNTIL: leave when true): its cost and the
        predicted back edge each pass, the misprediction when it leaves."""
        c0 = self.cost
        c = self.cond(expression, pre)
        self._emit(pre, indent)
        self._charge(self.cost - c0 + COSTS["loop"], indent)
        self.cost = c0
        self._line(f"if {c}:" if when_true else f"if not {c}:", indent)
        self._charge(COSTS["branch"], indent + 1)
        self._line("break", indent + 1)

    def _charge(self, cycles: int, indent: int) -> None:
        """Add ``cycles`` of the cost model (cost_model.COSTS) to the cycle's work where this line runs."""
        if cycles:
            self._line(f"_W[4] += {cycles}", indent)

    def _emit(self, pre: list[str], indent: int) -> None:
        for line in pre:
            self._line(line, indent)
        pre.clear()

    def _tmp(self) -> str:
        self.tmp += 1
        return f"t{self.tmp}_"

    def _assign(self, lv: LV, e: E, indent: int) -> None:
        t = lv.t
        self.cost += COSTS["store"] + (COSTS["convert"] if t.kind == "real" and e.t.kind != "real"
                                       and e.const is _NOCONST else 0)
        if not t.scalar or t.kind == "string":
            src = e.addr if hasattr(e, "addr") else None
            if t.kind == "string":
                self._line(f"_strcpy({lv.addr}, {t.size}, {self._string_src(e)})", indent)
                return
            if src is None:
                raise PlcCompileError(f"{self.pou.name}: cannot assign {e.t.name} to {t.name}")
            if e.t.size != t.size or e.t.kind != t.kind:
                raise PlcCompileError(f"{self.pou.name}: type mismatch {e.t.name} := {t.name}")
            self._line(f"_copy({lv.addr}, {src}, {t.size})", indent)
            return
        if t.kind == "real" and e.arith and e.t.kind == "real":
            # the NaN check inline (a call per assignment costs more than the arithmetic)
            if lv.local is not None:
                self._line(f"{lv.local} = {e.code}", indent)
                self._line(f"if {lv.local} != {lv.local}: _nanerr()", indent)
            else:
                tmp = self._tmp()
                self._line(f"{tmp} = {e.code}", indent)
                self._line(f"if {tmp} != {tmp}: _nanerr()", indent)
                self._line(lv.write(tmp), indent)
            return
        self._line(lv.write(self.coerce(e, t)), indent)

    def _check_write_access(self, target) -> None:
        """Refuse an assignment from outside to a program's or FB instance's own variable (VAR, VAR_OUTPUT,
        ...): TwinCAT reports it as a compile error and lets only the inputs be written (Infosys Static
        Analysis SA0102, /content/1033/te1200_tc3_plcstaticanalysis/20911240331.html: "TwinCAT determines
        external write access operations to local variables of programs or function blocks as compilation
        errors"). The member selected from the innermost instance on the path is the one written."""
        if type(target).__name__ != "MultiElementVariable" or self.pou.unit.file == LIBRARY_FILE:
            return
        found = self.lookup(str(target.name.name))
        if found is None or found[0] not in ("pou", "var", "global", "gvl"):
            return
        t = found[1].itype if found[0] == "pou" else None if found[0] == "gvl" else found[1].t
        written = None
        for el in target.elements:
            if type(el).__name__ != "FieldSelector":
                t = t.elem if t is not None and t.kind == "array" else None
                continue
            name = str(el.field.name)
            if t is None and found[0] == "gvl":
                gv = self.prog.gvls[found[1]].get(name.lower())
                t = gv.t if gv is not None else None
                continue
            if t is None or t.kind not in ("fb", "program", "struct", "union"):
                return
            if t.kind in ("fb", "program"):
                written = t.pou.vars.get(name.lower())
                written = (t.pou, written) if written is not None else None
            m = _member(t, name)
            t = m[1] if m is not None else None
        if written is not None and written[1].block != "VAR_INPUT" and written[0] not in (self.pou, self.pou.parent):
            owner, v = written
            raise PlcCompileError(f"{self.pou.name}: {owner.name}.{v.name} ({v.block}) is written from outside: "
                                  "TwinCAT lets only inputs be written (Infosys SA0102)")

    def _string_src(self, e: E) -> str:
        if e.const is not _NOCONST:
            return repr(e.const)
        if hasattr(e, "addr"):
            return f"_cstr({e.addr})"
        if e.t.kind == "string":                   # a string constant, by name (overridable): bytes
            return e.code
        raise PlcCompileError(f"{self.pou.name}: not a string")

    def coerce(self, e: E, t: DType) -> str:
        """Code for storing ``e`` into a variable of type ``t``: wraps integers, checks real results for NaN."""
        if t.kind == "real":
            if e.t.kind == "real" or e.t is ANYINT:
                code = e.code if e.t.kind == "real" else f"float({e.code})"
                if e.arith:
                    return f"_nan({code})"
                return code
            raise PlcCompileError(f"{self.pou.name}: implicit conversion {e.t.name} -> {t.name} (use {e.t.name}_TO_{t.name})")
        if t.kind == "bool":
            return e.code
        if t.kind == "enum" and t.strict and e.t is not t:
            raise PlcCompileError(f"{self.pou.name}: {e.t.name} assigned to {t.name}, a {STRICT_RULE}")
        if t.kind in ("int", "enum", "pointer", "reference"):
            if e.t.kind == "real":
                raise PlcCompileError(f"{self.pou.name}: implicit conversion {e.t.name} -> {t.name}")
            if e.const is not _NOCONST and isinstance(e.const, int):
                return repr(t.wrap(e.const) if t.kind != "enum" else e.const)
            if t.kind == "enum" and e.t.kind == "enum":
                return e.code
            if getattr(e, "plain", False) and e.t.kind in ("int", "enum", "pointer", "reference") and _fits(e.t, t):
                return e.code                       # a variable read that fits: nothing to wrap
            return t.wrap_code(e.code)
        return e.code

    # ---------------------------------------------------------------- lvalues and names
    def var_lv(self, v: Var, this: str = "this") -> LV:
        pou = self.pou
        if v.local is not None:
            return LV(v.t, local=v.local)
        if v.block == "VAR_IN_OUT":
            if pou.kind in ("function", "method") and pou.vars.get(v.name.lower()) is v:
                return LV(v.t, addr=f"a_{v.name}")
            return LV(v.t, addr=f"_Uq(mem, {addr_add(this, v.offset)})[0]")
        if v.location is not None:
            return LV(v.t, addr=str(self.prog.m_area[0] + v.offset))
        owner = pou
        if pou.kind in ("function", "method") and pou.vars.get(v.name.lower()) is v:
            return LV(v.t, addr=str(pou.frame_addr + v.offset), ref=v.t.kind == "reference")
        if owner is not None and owner.kind == "method":
            owner = owner.parent
        if owner is not None and owner.kind == "program" and this == "this":
            return LV(v.t, addr=str(self.prog.instances[owner.name.lower()] + v.offset), ref=v.t.kind == "reference")
        return LV(v.t, addr=addr_add(this, v.offset), ref=v.t.kind == "reference")

    def lookup(self, name: str):
        """Resolve a bare name: a local/member Var, a GlobalVar, a constant, a type, a POU, or a GVL."""
        key = name.lower()
        pou = self.pou
        scopes = []
        if pou is not None:
            scopes.append(pou)
            if pou.parent is not None:
                scopes.append(pou.parent)
        for s in scopes:
            if key in s.vars:
                v = s.vars[key]
                if v.block == "VAR_CONSTANT":
                    return ("const", f"{s.name}.{v.name}".lower())
                return ("var", v, s)
            if s is pou and pou.kind in ("function", "method") and key == pou.name.lower():
                return ("ret", pou)
        for gvl, names in self.prog.gvls.items():
            if gvl not in self.prog.qualified and key in names:
                return ("global", names[key])
        if key in self.prog.pous:
            return ("pou", self.prog.pous[key])
        if key in self.prog.gvls or any(k.split(".")[0] == key for k in self.prog.constants):
            return ("gvl", key)
        if key in self.prog.types:
            return ("type", self.prog.types[key])
        if key in self._dut_units:
            return ("type", self.type_named(key))
        return None

    def lvalue(self, node, pre: list, raw_ref: bool = False) -> LV:
        r = self.reference(node, pre, raw_ref=raw_ref)
        if not isinstance(r, LV):
            raise PlcCompileError(f"{self.pou.name if self.pou else ''}: {node} is not a variable")
        return r

    def reference(self, node, pre: list, raw_ref: bool = False):
        """An LV for a variable reference, or an E for a constant (enum value, GVL constant)."""
        kind = type(node).__name__
        if kind == "SimpleVariable":
            base, elements = str(node.name), []
            deref = node.dereferenced
        elif kind == "MultiElementVariable":
            base, elements = str(node.name.name), list(node.elements)
            deref = node.name.dereferenced
        else:
            raise PlcCompileError(f"{self.pou.name}: {kind} is not a variable")
        found = self.lookup(base)
        if found is None:
            raise PlcCompileError(f"{self.pou.name if self.pou else ''}: unknown name {base}")
        what = found[0]
        if what == "const":
            value, t, py = self.prog.constants[found[1]]
            return E(py, t, const=value if self.pou is None or not (t.scalar or t.kind == "string") else _NOCONST)   # overridable
        if what in ("global", "pou"):
            self.pure = False
        if what == "ret":
            lv = LV(found[1].ret, local="r_")
        elif what == "var":
            v, owner = found[1], found[2]
            lv = self.var_lv(v)
        elif what == "global":
            gv = found[1]
            lv = LV(gv.t, addr=str(gv.addr), ref=gv.t.kind == "reference")
        elif what in ("gvl", "type", "pou"):
            if not elements or type(elements[0]).__name__ != "FieldSelector":
                raise PlcCompileError(f"{self.pou.name if self.pou else ''}: {base} needs a member")
            member = str(elements[0].field.name)
            elements = elements[1:]
            if what == "gvl":
                ckey = f"{base}.{member}".lower()
                if ckey in self.prog.constants:
                    value, t, py = self.prog.constants[ckey]
                    if elements:
                        raise PlcCompileError(f"{self.pou.name}: member of a constant {ckey}")
                    return E(py, t, const=value if self.pou is None or not (t.scalar or t.kind == "string") else _NOCONST)   # overridable
                gv = self.prog.gvls[found[1]].get(member.lower())
                self.pure = False
                if gv is None:
                    raise PlcCompileError(f"unknown {base}.{member}")
                lv = LV(gv.t, addr=str(gv.addr), ref=gv.t.kind == "reference")
            elif what == "type":
                t = found[1]
                if t.kind != "enum":
                    raise PlcCompileError(f"{base}.{member}: not an enum value")
                return E(str(t.values[member.lower()]), t, const=t.values[member.lower()])
            else:
                pou = found[1]
                if pou.kind != "program":
                    raise PlcCompileError(f"{base}.{member}: not a program variable")
                v = pou.vars[member.lower()]
                lv = LV(v.t, addr=str(self.prog.instances[pou.name.lower()] + v.offset), ref=v.t.kind == "reference")
        else:
            raise PlcCompileError(f"{base}: not a variable")
        cost0 = self.cost
        if deref:
            lv = self._deref(lv, pre)
        for el in elements:
            if lv.ref or (lv.t.kind == "reference" and not raw_ref):
                lv = self._deref(lv, pre)
            ek = type(el).__name__
            if ek == "FieldSelector":
                fname = str(el.field.name)
                t = lv.t
                if t.kind not in ("struct", "union", "fb", "program"):
                    raise PlcCompileError(f"{self.pou.name}: .{fname} of {t.name}")
                m = _member(t, fname)
                if m is None:
                    raise PlcCompileError(f"{self.pou.name}: {t.name} has no member {fname}")
                off, mt = m
                lv = LV(mt, addr=addr_add(self._addr(lv), off), ref=mt.kind == "reference",
                        align=min(lv.align, lowbit(off)))
            elif ek == "SubscriptList" and lv.t.kind == "pointer":
                # p[i]: element i of what the pointer points to (TwinCAT pointer indexing)
                if len(el.subscripts) != 1:
                    raise PlcCompileError(f"{self.pou.name}: one index for a pointer")
                target = self._deref(lv, pre)
                ie = self.expr(el.subscripts[0], pre)
                self.cost += COSTS["index"]
                lv = LV(lv.t.elem, addr=f"_ptr({target.addr} + ({ie.code}) * {lv.t.elem.size})", align=1)
            elif ek == "SubscriptList":
                t = lv.t
                if t.kind != "array":
                    raise PlcCompileError(f"{self.pou.name}: index into {t.name}")
                if len(el.subscripts) != len(t.dims):
                    raise PlcCompileError(f"{self.pou.name}: {len(el.subscripts)} indices for {t.name}")
                const_off, parts, align = 0, [], lv.align
                for sub, (lo, hi), stride in zip(el.subscripts, t.dims, strides(t)):
                    ie = self.expr(sub, pre)
                    if ie.const is not _NOCONST:
                        if not lo <= ie.const <= hi:
                            raise PlcCompileError(f"{self.pou.name}: index {ie.const} outside {lo}..{hi}")
                        const_off += (ie.const - lo) * stride
                    else:
                        parts.append(f"_ix({ie.code}, {lo}, {hi}) * {stride}")
                        align = min(align, lowbit(stride))
                code = addr_add(self._addr(lv), const_off)
                self.cost += COSTS["index"] * len(parts)
                if parts:
                    code = f"{code} + " + " + ".join(parts)
                lv = LV(t.elem, addr=code, ref=t.elem.kind == "reference", align=min(align, lowbit(const_off)))
            else:
                raise PlcCompileError(f"{self.pou.name}: {ek} is not supported")
            if getattr(el, "dereferenced", False):
                lv = self._deref(lv, pre)
        if lv.ref and not raw_ref:
            lv = self._deref(lv, pre)
        # an address computed at run time (a variable index or a pointer) makes the access an L2 one
        self.last_far = self.cost != cost0 or "_ix(" in str(lv.addr) or "_ptr(" in str(lv.addr)
        return lv

    def _addr(self, lv: LV) -> str:
        if lv.local is not None:
            raise PlcCompileError(f"{self.pou.name}: the address of local {lv.local[2:]} is taken (interpreter limit)")
        return lv.addr if lv.addr.isdigit() or lv.addr.startswith("a_") or lv.addr == "this" else f"({lv.addr})"

    def _deref(self, lv: LV, pre: list | None = None) -> LV:
        """The target of a pointer/reference variable. Within one statement (or one condition) the
        pointer is loaded once (a statement that calls anything but pure functions loads it at each use)."""
        if lv.t.kind not in ("pointer", "reference"):
            raise PlcCompileError(f"{self.pou.name}: dereference of {lv.t.name}")
        self.pure = False
        self.cost += COSTS["load"]                        # the pointer itself
        code = f"_ptr({lv.read()})"
        if self.hoist is not None and pre is not None and lv.local is None:
            if code not in self.hoist:
                tmp = self._tmp()
                pre.append(f"{tmp} = {code}")
                self.hoist[code] = tmp
            code = self.hoist[code]
        return LV(lv.t.elem, addr=code, ref=False, align=1)

    def address_of(self, node, pre) -> str:
        lv = self.lvalue(node, pre)
        return self._addr(lv)

    # ---------------------------------------------------------------- expressions
    def cond(self, node, pre) -> str:
        mark, tmp, calls, cost = len(pre), self.tmp, self.math_calls, self.cost
        saved = self.hoist, self.impure_call
        self.hoist, self.impure_call = {}, False
        try:
            e = self.expr(node, pre)
            if self.impure_call and self.hoist:          # compile again without hoisting
                del pre[mark:]
                self.tmp, self.math_calls, self.hoist, self.cost = tmp, calls, None, cost
                e = self.expr(node, pre)
        finally:
            self.hoist, self.impure_call = saved
        if e.t.kind != "bool":
            raise PlcCompileError(f"{self.pou.name}: condition of type {e.t.name}")
        return e.code

    def expr(self, node, pre: list) -> E:
        kind = type(node).__name__
        if kind in ("Integer", "HexInteger", "BinaryInteger", "OctalInteger"):
            v = int(str(node.value).replace("_", ""), node.base)
            t = self.type_named(str(node.type_name)) if node.type_name else ANYINT
            if t.kind == "real":
                return E(repr(float(v)), t, const=float(v))
            return E(str(v), t, const=v)
        if kind in ("BitString", "HexBitString", "BinaryBitString", "OctalBitString"):
            v = int(str(node.value).replace("_", ""), node.base)
            t = self.type_named(str(node.type_name)) if node.type_name else ANYINT
            return E(str(v), t, const=v)
        if kind == "Real":
            v = float(str(node.value).replace("_", ""))
            t = self.type_named(str(node.type_name)) if node.type_name else LREAL
            return E(_pyrepr(v), t, const=v)
        if kind == "Boolean":
            v = str(node.value).upper() in ("TRUE", "1")
            return E(repr(v), BOOL, const=v)
        if kind == "Duration":
            v = duration_ms(node)
            return E(str(v), TIME, const=v)
        if kind == "String":
            v = _st_string(str(node.value))
            e = E(repr(v), string_type(len(v)), const=v)
            return e
        if kind == "EnumeratedValue":
            tname = str(node.type_name) if node.type_name else ""
            vname = str(node.name)
            if not tname and "." in vname:
                tname, vname = vname.rsplit(".", 1)
            if tname:
                t = self.type_named(tname)
                return E(str(t.values[vname.lower()]), t, const=t.values[vname.lower()])
            raise PlcCompileError(f"{self.pou.name}: unqualified enum value {vname}")
        if kind == "ParenthesizedExpression":
            e = self.expr(node.expr, pre)
            return E(f"({e.code})", e.t, e.arith, e.const)
        if kind in ("SimpleVariable", "MultiElementVariable"):
            r = self.reference(node, pre)
            if isinstance(r, E):
                return r
            if not r.t.scalar or r.t.kind == "string":
                e = E("None", r.t)
                e.addr = self._addr(r)
                return e
            self.cost += COSTS["load_far"] if self.last_far else COSTS["load"]
            e = E(r.read(), r.t)
            e.plain = True
            e.computed = False
            return e
        if kind == "UnaryOperation":
            return self._unary(node, pre)
        if kind == "BinaryOperation":
            return self._binary(node, pre)
        if kind == "FunctionCall":
            e = self.call(node, pre)
            if e is None:
                raise PlcCompileError(f"{self.pou.name}: {node.name} returns nothing")
            return e
        raise PlcCompileError(f"{self.pou.name if self.pou else ''}: expression {kind} is not supported")

    def _unary(self, node, pre) -> E:
        op = str(node.op).upper()
        e = self.expr(node.expr, pre)
        if op != "+" and e.const is _NOCONST:
            self.cost += COSTS["alu"]
        if op == "NOT":
            if e.t.kind == "bool":
                return E(f"(not {e.code})", BOOL, const=(not e.const) if e.const is not _NOCONST else _NOCONST)
            if e.t is ANYINT or e.t.bits >= REGISTER_BITS:
                return E(f"({e.code} ^ {(1 << e.t.bits) - 1:#x})", e.t)
            # x64: the whole 64-bit register is complemented and not truncated to the type until stored
            # (a signed value is sign-extended, so ~x; an unsigned one zero-extended, so its upper bits turn 1)
            return E(f"(~{e.code})" if e.t.signed else f"({e.code} ^ {(1 << REGISTER_BITS) - 1:#x})", e.t)
        if op == "-":
            const = -e.const if e.const is not _NOCONST else _NOCONST
            out = E(f"(-{e.code})", e.t, e.arith, const)
            return out
        if op == "+":
            return e
        raise PlcCompileError(f"{self.pou.name}: unary {op}")

    def _binary(self, node, pre) -> E:
        op = str(node.op).upper()
        a = self.expr(node.left, pre)
        b = self.expr(node.right, pre)
        const = a.const is not _NOCONST and b.const is not _NOCONST
        if not const:
            self.cost += _op_cost(op, a.t.kind == "real" or b.t.kind == "real",
                                  a.t.kind == "string" or b.t.kind == "string")
        if op in ("AND", "OR", "XOR", "AND_THEN", "OR_ELSE"):
            if a.t.kind == "bool" and b.t.kind == "bool":
                py = {"AND": "&", "OR": "|", "XOR": "^", "AND_THEN": "and", "OR_ELSE": "or"}[op]
            else:
                py = {"AND": "&", "OR": "|", "XOR": "^"}[op]
            t = a.t if a.t is not ANYINT else b.t
            code = f"({a.code} {py} {b.code})"
            return E(code, t, const=eval(code, {}) if const else _NOCONST)
        if op in ("=", "<>", "<", ">", "<=", ">="):
            if a.t.kind == "string" or b.t.kind == "string":
                if a.t.kind != b.t.kind or op not in ("=", "<>"):
                    raise PlcCompileError(f"{self.pou.name if self.pou else ''}: {op} of a STRING with a "
                                          f"{b.t.name if a.t.kind == 'string' else a.t.name}")
                # by value, up to the terminating NUL (STRING(n) = STRING(m) compares the text)
                code = f"({self._string_src(a)} {'==' if op == '=' else '!='} {self._string_src(b)})"
                return E(code, BOOL, const=eval(code, {}) if const else _NOCONST)
            if a.t.kind == "real" or b.t.kind == "real":
                # a comparison that is FALSE (TRUE for <>) may have a NaN operand: only then a call checks it
                ta, tb = (a.code, b.code) if _simple(a.code) and _simple(b.code) else (self._tmp(), self._tmp())
                wa = a.code if ta == a.code else f"({ta} := {a.code})"
                wb = b.code if tb == b.code else f"({tb} := {b.code})"
                if op == "<>":
                    return E(f"({wa} != {wb} and _cmp_ne({ta}, {tb}))", BOOL)
                py = {"=": "==", "<": "<", ">": ">", "<=": "<=", ">=": ">="}[op]
                return E(f"({wa} {py} {wb} or _cmp_false({ta}, {tb}))", BOOL)
            py = {"=": "==", "<>": "!="}.get(op, op)
            code = f"({a.code} {py} {b.code})"
            return E(code, BOOL, const=eval(code, {}) if const else _NOCONST)
        strict = next((x.t for x in (a, b) if x.t.kind == "enum" and x.t.strict), None)
        if strict is not None:
            raise PlcCompileError(f"{self.pou.name}: {op} on {strict.name}, a {STRICT_RULE}")
        real = a.t.kind == "real" or b.t.kind == "real"
        if real:
            t = LREAL if (a.t.name == "LREAL" or b.t.name == "LREAL" or a.t is ANYINT or b.t is ANYINT) else REAL
        else:
            t = _wider(a.t, b.t)
        if op in ("+", "-", "*"):
            code = f"({a.code} {op} {b.code})"
        elif op == "/":
            code = f"({a.code} / {b.code})" if real else f"_idiv({a.code}, {b.code})"
        elif op == "MOD":
            if real:                # TwinCAT: C0208 'MOD' is not defined for 'REAL' (ANY_INT operands only)
                raise PlcCompileError(f"{self.pou.name}: MOD of {a.t.name} and {b.t.name}: MOD takes integers only "
                                      "(Infosys tc3_plc_intro, MOD, /content/1033/tc3_plc_intro/2528880779.html)")
            code = f"_imod({a.code}, {b.code})"
        elif op == "**":
            self.math_calls += 1
            code = f"_expt({a.code}, {b.code})"
            real, t = True, LREAL
        else:
            raise PlcCompileError(f"{self.pou.name}: operator {op}")
        value = _NOCONST
        if const:
            value = _const_eval(code)
            if not real and isinstance(value, int) and t is not ANYINT:
                value = t.wrap(value)
            if value is not _NOCONST:
                return E(_pyrepr(value), t, const=value, arith=real and value != value)
        return E(code, t, arith=real)

    # ---------------------------------------------------------------- calls
    def call(self, node, pre: list, statement: bool = False) -> E | None:
        name_node = node.name
        nkind = type(name_node).__name__
        params = list(node.parameters or [])
        if nkind == "SimpleVariable":
            name = str(name_node.name)
            from pmcal.bridge.simulator.plc_runtime.builtins import BUILTINS
            if name.upper() in BUILTINS or _is_conversion(name):
                return self._builtin(name.upper(), params, pre)
            owner = self.pou.parent if self.pou.kind == "method" else self.pou
            if owner is not None and name.lower() in owner.methods:
                return self._call_method(owner.methods[name.lower()], "this", params, pre)
            found = self.lookup(name)
            if found is None:
                raise PlcCompileError(f"{self.pou.name}: unknown function {name}")
            if found[0] == "pou" and found[1].kind == "function":
                return self._call_function(found[1], params, pre)
            if found[0] == "pou" and found[1].kind == "program":
                pou = found[1]
                self.impure_call = True
                self.cost += COSTS["call"]
                self._store_inputs(pou, str(self.prog.instances[pou.name.lower()]), params, pre)
                pre.append(f"{pou.pyname}({self.prog.instances[pou.name.lower()]})")
                self._read_outputs(pou, str(self.prog.instances[pou.name.lower()]), params, pre)
                return E("None", BOOL)
            # an FB instance
            lv = self.lvalue(name_node, pre)
            return self._call_fb(lv, params, pre)
        if nkind == "MultiElementVariable":
            *path, last = name_node.elements
            if type(last).__name__ != "FieldSelector":
                raise PlcCompileError(f"{self.pou.name}: call of {name_node}")
            method = str(last.field.name)
            inst_node = type(name_node)(name=name_node.name, dereferenced=name_node.dereferenced, elements=path) \
                if path else name_node.name
            lv = self.lvalue(inst_node, pre)
            if lv.t.kind not in ("fb", "program") or method.lower() not in lv.t.pou.methods:
                # an FB instance inside a struct/array: call it
                lv2 = self.lvalue(name_node, pre)
                return self._call_fb(lv2, params, pre)
            return self._call_method(lv.t.pou.methods[method.lower()], self._addr(lv), params, pre)
        raise PlcCompileError(f"{self.pou.name}: call of {nkind}")

    def _bind(self, pou: Pou, params) -> tuple[dict, list]:
        """Inputs by name (positional ones in declaration order) and the output assignments."""
        inputs, outputs = {}, []
        decl = pou.params
        for i, p in enumerate(params):
            pk = type(p).__name__
            if pk == "OutputParameterAssignment":
                outputs.append((str(p.name.name), p.value, p.inverted))
                continue
            if p.name is None:
                if i >= len(decl):
                    raise PlcCompileError(f"{self.pou.name}: too many arguments for {pou.name}")
                inputs[decl[i].name.lower()] = p.value
            else:
                inputs[str(p.name.name).lower()] = p.value
        for k in inputs:
            if k not in pou.vars or pou.vars[k].block not in ("VAR_INPUT", "VAR_IN_OUT"):
                raise PlcCompileError(f"{self.pou.name}: {pou.name} has no input {k}")
        return inputs, outputs

    def _args(self, pou: Pou, inputs: dict, pre) -> list[str]:
        args = []
        for v in pou.order:
            if v.block == "VAR_INPUT":
                if v.name.lower() in inputs:
                    args.append(self.coerce(self.expr(inputs[v.name.lower()], pre), v.t))
                else:
                    args.append(repr(self.const_value(v.init, v.t)) if v.init is not None else repr(_zero(v.t)))
            elif v.block == "VAR_IN_OUT":
                if v.name.lower() not in inputs:
                    raise PlcCompileError(f"{self.pou.name}: {pou.name} needs VAR_IN_OUT {v.name}")
                args.append(self.address_of(inputs[v.name.lower()], pre))
        return args

    def _outputs(self, pou: Pou, result: str, outputs, pre) -> None:
        outs = [v for v in pou.order if v.block == "VAR_OUTPUT"]
        names = [v.name.lower() for v in outs]
        for oname, target, inverted in outputs:
            if oname.lower() not in names:
                raise PlcCompileError(f"{self.pou.name}: {pou.name} has no output {oname}")
            k = names.index(oname.lower()) + 1
            lv = self.lvalue(target, pre)
            value = f"{result}[{k}]"
            pre.append(lv.write(f"(not {value})" if inverted else value))

    def _call_function(self, pou: Pou, params, pre) -> E:
        if pou.name.lower() not in self.prog.pure:
            self.pure = False
            self.impure_call = True
        inputs, outputs = self._bind(pou, params)
        args = self._args(pou, inputs, pre)
        self.cost += COSTS["call"] + COSTS["store"] * (len(args) + len(outputs))
        code = f"{pou.pyname}({', '.join(args)})"
        has_outs = any(v.block == "VAR_OUTPUT" for v in pou.order)
        if has_outs:
            tmp = self._tmp()
            pre.append(f"{tmp} = {code}")
            self._outputs(pou, tmp, outputs, pre)
            code = f"{tmp}[0]"
        e = E(code, pou.ret or BOOL)
        if pou.ret is None:
            pre.append(code)
            return E("None", BOOL)
        return e

    def _call_method(self, m: Pou, this: str, params, pre) -> E:
        self.pure = False
        self.impure_call = True
        inputs, outputs = self._bind(m, params)
        args = [this] + self._args(m, inputs, pre)
        self.cost += COSTS["call"] + COSTS["store"] * (len(args) + len(outputs))
        code = f"{m.pyname}({', '.join(args)})"
        if any(v.block == "VAR_OUTPUT" for v in m.order):
            tmp = self._tmp()
            pre.append(f"{tmp} = {code}")
            self._outputs(m, tmp, outputs, pre)
            code = f"{tmp}[0]"
        if m.ret is None:
            pre.append(code)
            return E("None", BOOL)
        return E(code, m.ret)

    def _call_fb(self, lv: LV, params, pre) -> E:
        t = lv.t
        self.pure = False
        self.impure_call = True
        if t.kind not in ("fb", "program"):
            raise PlcCompileError(f"{self.pou.name}: call of {t.name}")
        pou = t.pou
        addr = self._addr(lv)
        if not addr.isdigit() and addr not in ("this",):
            tmp = self._tmp()
            pre.append(f"{tmp} = {addr}")
            addr = tmp
        self._store_inputs(pou, addr, params, pre)
        self.cost += COSTS["call"]
        pre.append(f"{pou.pyname}({addr})")
        self._read_outputs(pou, addr, params, pre)
        return E("None", BOOL)

    def _store_inputs(self, pou: Pou, addr: str, params, pre) -> None:
        inputs, _ = self._bind(pou, params)
        for k, value in inputs.items():
            v = pou.vars[k]
            if v.block == "VAR_IN_OUT":
                pre.append(store_code(POINTER, addr_add(addr, v.offset), self.address_of(value, pre)))
                continue
            e = self.expr(value, pre)
            self.cost += COSTS["store"]
            target = LV(v.t, addr=addr_add(addr, v.offset))
            if not v.t.scalar:
                if not hasattr(e, "addr"):
                    raise PlcCompileError(f"{self.pou.name}: aggregate input {k}")
                pre.append(f"_copy({target.addr}, {e.addr}, {v.t.size})")
            else:
                pre.append(target.write(self.coerce(e, v.t)))

    def _read_outputs(self, pou: Pou, addr: str, params, pre) -> None:
        _, outputs = self._bind(pou, params)
        for oname, target, inverted in outputs:
            v = pou.vars.get(oname.lower())
            if v is None or v.block != "VAR_OUTPUT":
                raise PlcCompileError(f"{self.pou.name}: {pou.name} has no output {oname}")
            src = LV(v.t, addr=addr_add(addr, v.offset)).read()
            self.cost += COSTS["load"] + COSTS["store"]
            lv = self.lvalue(target, pre)
            pre.append(lv.write(f"(not {src})" if inverted else src))

    def _builtin(self, name: str, params, pre) -> E:
        from pmcal.bridge.simulator.plc_runtime.builtins import BUILTINS, conversion
        args = {}
        positional = []
        for p in params:
            if type(p).__name__ == "OutputParameterAssignment":
                raise PlcCompileError(f"{self.pou.name}: {name} has no outputs")
            if p.name is None:
                positional.append(p.value)
            else:
                args[str(p.name.name).lower()] = p.value
        self.cost += _builtin_cost(name)
        if _is_conversion(name) and name not in BUILTINS:
            return conversion(self, name, positional or list(args.values()), pre)
        spec = BUILTINS[name]
        if spec.memory or spec.simulation:
            self.pure = False
            self.impure_call = self.impure_call or spec.memory
        if spec.nonstandard:
            self.prog.nonstandard.setdefault(name, set()).add(self.pou.name if self.pou else "")
        return spec.compile(self, positional, args, pre)


# ====================================================================== helpers
#: operators of one cost class (cost_model.COSTS)
_TRANSCENDENTAL = {"SIN", "COS", "TAN", "ASIN", "ACOS", "ATAN", "ATAN2", "EXP", "LN", "LOG", "EXPT"}
_SELECT = {"MIN", "MAX", "LIMIT", "SEL", "MUX"}
_FREE = {"ADR", "SIZEOF"}


def _builtin_cost(name: str) -> int:
    """Cycles of an operator or library call (its arguments are charged as they are compiled; the bytes
    a memory function moves are counted at run time)."""
    if name in _TRANSCENDENTAL:
        return COSTS["transcendental"]
    if name == "SQRT":
        return COSTS["fp_div"]
    if name in _SELECT:
        return 2 * COSTS["fp_cmp"]                             # compare and conditional move, twice at most
    if name in _FREE:
        return 0
    if name.startswith("TRUNC") or (_is_conversion(name) and "REAL" in name):
        return COSTS["convert"]
    if _is_conversion(name) or name in ("ABS", "SHL", "SHR", "ROL", "ROR"):
        return COSTS["alu"]
    return COSTS["call"]                                       # MEMCPY, MEMSET, MEMCMP, CRC, hooks


def _op_cost(op: str, real: bool, string: bool) -> int:
    """Cycles of a binary operator (cost_model.COSTS): by operator and operand kind."""
    if string:
        return COSTS["call"]                                   # a string compare is a library call
    if op in ("AND", "OR", "XOR", "AND_THEN", "OR_ELSE"):
        return COSTS["alu"]
    if op in ("=", "<>", "<", ">", "<=", ">="):
        return COSTS["fp_cmp"] if real else COSTS["alu"]
    if op in ("+", "-"):
        return COSTS["fp_add"] if real else COSTS["alu"]
    if op == "*":
        return COSTS["fp_mul"] if real else COSTS["int_mul"]
    if op in ("/", "MOD"):
        return COSTS["fp_div"] if real else COSTS["int_div"]
    return COSTS["transcendental"]                             # **


def _split_top(text: str, sep: str) -> list[str]:
    out, depth, cur = [], 0, ""
    for ch in text:
        depth += {"(": 1, "[": 1, ")": -1, "]": -1}.get(ch, 0)
        if ch == sep and depth == 0:
            out.append(cur)
            cur = ""
        else:
            cur += ch
    out.append(cur)
    return out


def _pyrepr(value) -> str:
    """Python source for a constant (also +-inf and NaN, which have no literal)."""
    if isinstance(value, float) and (value != value or value in (math.inf, -math.inf)):
        return f"float({str(value)!r})"
    return repr(value)


def _simple(code: str) -> bool:
    """A Python local, a constant name or a literal: cheap and free of side effects to evaluate twice."""
    c = code.strip("()")
    return c.replace("_", "").replace(".", "").replace("-", "").isalnum() and "(" not in code[1:-1]


def _member(t: DType, name: str):
    for k, v in t.members.items():
        if k.lower() == name.lower():
            return v
    return None


def _wider(a: DType, b: DType) -> DType:
    if a is ANYINT:
        return b
    if b is ANYINT:
        return a
    return a if a.size >= b.size else b


def _fits(src: DType, dst: DType) -> bool:
    """Every value of integer type ``src`` is a value of ``dst`` (no wrap needed)."""
    if src.kind == "enum" or dst.kind == "enum":
        return src.size <= dst.size
    if src.signed == dst.signed:
        return src.size <= dst.size
    return not src.signed and src.size < dst.size


def _zero(t: DType):
    if t.kind == "real":
        return 0.0
    if t.kind == "bool":
        return False
    if t.kind == "string":
        return b""
    if t.scalar:
        return 0
    return None


def _st_string(text: str) -> bytes:
    s = text[1:-1] if text[:1] in "'\"" else text
    out, i = bytearray(), 0
    while i < len(s):
        if s[i] == "$" and i + 1 < len(s):
            c = s[i + 1]
            esc = {"$": b"$", "'": b"'", "L": b"\n", "N": b"\n", "P": b"\f", "R": b"\r", "T": b"\t"}
            if c.upper() in esc:
                out += esc[c.upper()]
                i += 2
                continue
            out += bytes([int(s[i + 1:i + 3], 16)])
            i += 3
            continue
        out += s[i].encode("latin-1")
        i += 1
    return bytes(out)


def _poke(image: bytearray, addr: int, t: DType, value) -> None:
    import struct
    if t.kind == "string":
        data = bytes(value)[:t.size - 1]
        image[addr:addr + len(data)] = data
        return
    if t.kind == "bool":
        image[addr] = 1 if value else 0
        return
    if not t.scalar:
        raise PlcCompileError(f"initial value for {t.name}")
    if t.kind in ("int", "enum", "pointer"):
        value = t.wrap(int(value)) if t.kind != "enum" else int(value)
    struct.pack_into("<" + t.fmt, image, addr, value)


def _is_init_struct(init) -> bool:
    return type(init).__name__ in ("StructureInitialization", "ArrayInitialization")


def _is_conversion(name: str) -> bool:
    up = name.upper()
    if "_TO_" in up:
        return True
    return up.startswith("TO_") and up[3:] in ELEMENTARY


def _const_eval(code: str):
    from pmcal.bridge.simulator.plc_runtime import builtins as b
    try:
        return eval(code, b.namespace_for_constants())  # noqa: S307 - our own generated arithmetic
    except Exception:   # division by zero etc.: left to run time
        return _NOCONST


def _jumps(stmt) -> bool:
    """True if ``stmt`` may leave its block early (RETURN/EXIT/CONTINUE anywhere inside)."""
    kind = type(stmt).__name__
    if kind in ("ReturnStatement", "ExitStatement", "ContinueStatement", "JumpStatement"):
        return True
    if kind in ("AssignmentStatement", "FunctionCallStatement", "NoOpStatement", "ReferenceAssignmentStatement"):
        return False
    for attr in ("statements", "else_clause", "else_ifs", "cases"):
        sub = getattr(stmt, attr, None)
        if sub is None:
            continue
        subs = sub if isinstance(sub, list) else [sub]
        for s in subs:
            inner = getattr(s, "statements", s)
            inner = getattr(inner, "statements", inner)
            if isinstance(inner, list) and any(_jumps(x) for x in inner):
                return True
            if kind in ("ForStatement", "WhileStatement", "RepeatStatement"):
                # EXIT inside a loop only leaves that loop
                continue
    return False


def _addressed_names(body) -> set[str]:
    """Lower-case names whose address is taken in ``body`` (ADR(x...), x passed to REF=)."""
    out: set[str] = set()

    def visit(node, in_adr=False):
        if node is None:
            return
        if isinstance(node, list):
            for x in node:
                visit(x, in_adr)
            return
        kind = type(node).__name__
        if kind == "FunctionCall" or kind == "FunctionCallStatement":
            name = str(getattr(node.name, "name", "")).upper()
            for p in node.parameters or []:
                visit(getattr(p, "value", None), in_adr or name in ("ADR", "SIZEOF"))
            return
        if kind == "ReferenceAssignmentStatement":
            visit(node.expression, True)
            return
        if kind == "SimpleVariable" and in_adr:
            out.add(str(node.name).lower())
            return
        if kind == "MultiElementVariable" and in_adr:
            out.add(str(node.name.name).lower())
        if hasattr(node, "__dataclass_fields__"):
            for f in node.__dataclass_fields__:
                if f != "meta":
                    visit(getattr(node, f), in_adr)
    visit(body)
    return out
