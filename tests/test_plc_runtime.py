"""The ST interpreter (bridge.plc_runtime) against references that do not come from it: hand-computed
ST snippets (integer wrap, TON timing, traps), the byte offsets written in the DUT comments and in
bridge/plc_types.py, the CRC check values of the CRC catalogue (CRC-16/CCITT-FALSE 16#29B1,
CRC-32 16#CBF43926 for '123456789'), IEEE-754 results computed by hand."""

from __future__ import annotations

import math
import re
import struct
from pathlib import Path

import pytest

from pmcal.bridge import plc_types
from pmcal.bridge.simulator.plc_runtime import PlcRuntime, compile_files, compile_project
from pmcal.bridge.simulator.plc_runtime.cost_model import COSTS
from pmcal.bridge.simulator.plc_runtime.compiler import PlcCompileError

PLC = Path(__file__).resolve().parent.parent / "plc"


def run_st(tmp_path, source: str, cycles: int = 1, **kwargs) -> PlcRuntime:
    """Compile a PROGRAM MAIN (plus whatever else ``source`` declares) and run it ``cycles`` times."""
    path = tmp_path / "snippet.st"
    path.write_text(source)
    rt = PlcRuntime(compile_files([path]), task=("MAIN",), **kwargs)
    rt.run(cycles)
    return rt


#: an LREAL seen as its four WORDs (as plc/DUTs/U_CompTableLreal)
U_BITS = """
TYPE U_Bits :
UNION
    fValue : LREAL;
    aWord  : ARRAY[0..3] OF WORD;
END_UNION
END_TYPE
"""


def test_integers_wrap_to_their_type(tmp_path):
    rt = run_st(tmp_path, """
PROGRAM MAIN
VAR
    a : SINT := 127;  b : USINT := 0;  c : UINT := 65535;  d : DINT := 2147483647;
    e : UDINT := 0;   w : WORD;        q : INT := -32768;  l : LINT := 9223372036854775807;
    r1, r2, m1, m2 : DINT;
    s1 : WORD; s2 : BYTE;
END_VAR
a := a + 1;  b := b - 1;  c := c + 1;  d := d + 1;  e := e - 1;
w := NOT WORD#0;  q := -q;  l := l + 1;
r1 := -7 / 2;  r2 := 7 / -2;  m1 := -7 MOD 2;  m2 := 7 MOD -2;
s1 := SHL(WORD#16#8001, 1);  s2 := ROR(BYTE#1, 1);
END_PROGRAM
""")
    v = {k: rt.read_value(f"MAIN.{k}") for k in ("a", "b", "c", "d", "e", "w", "q", "l", "r1", "r2", "m1", "m2",
                                                 "s1", "s2")}
    assert v == dict(a=-128, b=255, c=0, d=-2**31, e=2**32 - 1, w=0xFFFF, q=-32768, l=-2**63,
                     r1=-3, r2=-3, m1=-1, m2=1, s1=0x0002, s2=0x80)


def test_ton_times_on_the_simulated_clock(tmp_path):
    src = """
PROGRAM MAIN
VAR
    ton : TON;  nQ : UDINT;  nCycle : UDINT;  bSeen : BOOL;
END_VAR
nCycle := nCycle + 1;
ton(IN := TRUE, PT := T#10MS);
IF ton.Q AND NOT bSeen THEN
    nQ := nCycle;
    bSeen := TRUE;
END_IF
END_PROGRAM
"""
    # cycle k (from 1) runs at clock (k-1) ms; the timer starts at 0 ms and is due at 10 ms: cycle 11
    assert run_st(tmp_path, src, cycles=30).read_value("MAIN.nQ") == 11
    # with a 4 ms cycle: clock 0, 4, 8, 12 -> the fourth cycle
    assert run_st(tmp_path, src, cycles=30, cycle_s=0.004).read_value("MAIN.nQ") == 4


@pytest.mark.parametrize("body, kind", [
    ("x := 1.0E308 * 10.0; y := x * 0.0;", "nan"),          # inf (overflow does not stop), then inf * 0
    ("x := 1.0E308 * 10.0; y := x - x;", "nan"),
    ("y := x / x;", "division"),                           # 0.0 / 0.0: division by zero
    ("y := 1.0 / x;", "division"),
    ("i := 7; k := i / j;", "division"),
    ("i := 7; k := i MOD j;", "division"),
    ("y := SQRT(-1.0);", "domain"),
    ("y := ACOS(1.5);", "domain"),
    ("u.aWord[3] := 16#7FF8; y := u.fValue; IF y < 1.0 THEN k := 1; END_IF", "nan"),   # a NaN compared
    ("u.aWord[3] := 16#7FF8; b := u.fValue = u.fValue;", "nan"),
    ("u.aWord[3] := 16#7FF0; k := TRUNC(u.fValue);", "conversion"),                   # +inf to DINT
])
def test_fpu_exceptions_stop_the_task(tmp_path, body, kind):
    rt = run_st(tmp_path, U_BITS + f"""PROGRAM MAIN
VAR
    x, y : LREAL;  i, j, k : DINT;  u : U_Bits;  b : BOOL;  nAfter : INT;
END_VAR
{body}
nAfter := 1;
END_PROGRAM
""", cycles=3)
    assert rt.stopped and rt.fault.kind == kind and rt.fault.cycle == 0
    assert rt.fault.where == "MAIN line 12"                 # the line of ``body`` in the snippet
    assert rt.read_value("MAIN.nAfter") == 0              # nothing after the trap ran
    assert rt.cycles == 1                                   # and the task stays stopped


def test_copying_a_nan_and_overflow_do_not_stop(tmp_path):
    rt = run_st(tmp_path, U_BITS + """PROGRAM MAIN
VAR
    u : U_Bits;  y, z, big : LREAL;  b : BOOL;
END_VAR
u.aWord[3] := 16#7FF8;          // quiet NaN bit pattern
y := u.fValue;                   // a copy: no arithmetic
big := 1.0E308 * 10.0;           // +inf: overflow is masked in TwinCAT
z := 5.0E-324 / 2.0;             // denormal underflow to 0: no exception
b := (u.aWord[3] AND 16#7FF0) = 16#7FF0;
END_PROGRAM
""")
    assert not rt.stopped
    assert math.isnan(rt.read_value("MAIN.y")) and rt.read_value("MAIN.big") == math.inf
    assert rt.read_value("MAIN.z") == 0.0 and rt.read_value("MAIN.b") is True


def test_and_evaluates_both_operands_and_then_does_not(tmp_path):
    src = """
PROGRAM MAIN
VAR
    x : LREAL;  u : ARRAY[0..3] OF WORD;  b : BOOL;  p : POINTER TO LREAL;
END_VAR
p := ADR(u);
u[3] := 16#7FF8;
b := FALSE {op} p^ > 0.0;
END_PROGRAM
"""
    assert run_st(tmp_path, src.replace("{op}", "AND")).stopped               # IEC: AND evaluates both sides
    assert not run_st(tmp_path, src.replace("{op}", "AND_THEN")).stopped


def test_crc_check_values(tmp_path):
    """CRC-16/CCITT-FALSE through the library function, CRC-32 (IEEE) written in ST: the catalogue's
    check values for '123456789'."""
    rt = run_st(tmp_path, """
FUNCTION F_Crc32 : DWORD
VAR_INPUT
    pData : POINTER TO BYTE;
    cbData : UDINT;
    nCrc : DWORD;
END_VAR
VAR
    i : UDINT;  b : INT;  c : DWORD;
END_VAR
c := nCrc XOR 16#FFFFFFFF;
FOR i := 0 TO cbData - 1 DO
    c := c XOR BYTE_TO_DWORD(pData[i]);
    FOR b := 0 TO 7 DO
        IF (c AND 1) <> 0 THEN
            c := SHR(c, 1) XOR 16#EDB88320;
        ELSE
            c := SHR(c, 1);
        END_IF
    END_FOR
END_FOR
F_Crc32 := c XOR 16#FFFFFFFF;
END_FUNCTION
PROGRAM MAIN
VAR
    s : STRING(9) := '123456789';  n16 : WORD;  n32 : DWORD;
END_VAR
n16 := F_DATA_TO_CRC16_CCITT(pData := ADR(s), cbData := 9, crc := 16#FFFF);
n32 := F_Crc32(pData := ADR(s), cbData := 9, nCrc := 0);
END_PROGRAM
""")
    assert (rt.read_value("MAIN.n16"), rt.read_value("MAIN.n32")) == (0x29B1, 0xCBF43926)
    assert rt.work_last["crc_bytes"] == 9


def test_work_counters(tmp_path):
    rt = run_st(tmp_path, """
PROGRAM MAIN
VAR
    a, b : ARRAY[0..99] OF LREAL;  i : INT;  x : LREAL;
END_VAR
MEMCPY(destAddr := ADR(a), srcAddr := ADR(b), n := SIZEOF(a));   // 800 bytes
FOR i := 0 TO 9 DO                                                // 1 statement ...
    x := SIN(x) + COS(x);                                         // ... + 10 x (1 statement, 2 calls)
END_FOR
a := b;                                                           // 800 bytes
END_PROGRAM
""")
    c = COSTS     # the cost model's cycles, by hand: the call, the loop (11 tests, 10 bodies, the exit), a := b
    loop = c["store"] + 11 * (2 * c["load"] + 2 * c["alu"] + c["loop"] + c["store"]) + c["branch"]
    body = 2 * (c["load"] + c["transcendental"]) + c["fp_add"] + c["store"]
    assert rt.work_last == {"statements": 13, "math_calls": 20, "bytes_copied": 1600, "crc_bytes": 0,
                            "cpu_cycles": c["call"] + loop + 10 * body + c["store"]}


def test_persistent_data_survive_a_restart_and_a_power_cut_loses_what_was_not_written(tmp_path):
    src = """
VAR_GLOBAL PERSISTENT
    nSaved : UDINT;
END_VAR
PROGRAM MAIN
VAR
    nVolatile : UDINT;  fbWrite : FB_WritePersistentData;  bWrite : BOOL;
END_VAR
nSaved := nSaved + 1;
nVolatile := nVolatile + 1;
fbWrite(PORT := 851, START := bWrite);
END_PROGRAM
"""
    rt = run_st(tmp_path, src, cycles=3)
    path = "GVL.nSaved"                                   # a GVL without a name in a plain .st file
    assert rt.read_value(path) == 3
    rt.restart()                                            # clean: persistent data written at shutdown
    assert (rt.read_value(path), rt.read_value("MAIN.nVolatile")) == (3, 0)
    rt.run(2)
    rt.power_cut()                                          # no write since the restart: back to 3
    assert rt.read_value(path) == 3
    rt.run(2)                                               # 5
    rt.write_value("MAIN.bWrite", True)
    rt.run(1)                                               # 6, the write starts (busy 5 cycles)
    assert rt.read_value("MAIN.fbWrite.BUSY")
    rt.power_cut()                                          # cut while busy: nothing saved
    assert rt.read_value(path) == 3
    rt.write_value("MAIN.bWrite", True)
    rt.run(1 + rt.persistent_write_cycles)                  # 4 .. 9: saved when the FB finishes
    assert not rt.read_value("MAIN.fbWrite.BUSY")
    saved = rt.read_value(path)
    rt.run(3)
    rt.power_cut()
    assert rt.read_value(path) == saved == 3 + 1 + rt.persistent_write_cycles


def _comment_offsets(dut: str) -> dict[str, int]:
    """Member -> byte offset as written in the DUT's comments (``name : TYPE; // 12 ...``)."""
    text = (PLC / "DUTs" / f"{dut}.TcDUT").read_text()
    return {m[1]: int(m[2]) for m in re.finditer(r"^\s*(\w+)\s*:[^;]+;\s*//\s*(\d+)", text, re.M)}


@pytest.mark.parametrize("dut, size", [
    ("ST_CompTableHeader", plc_types.HEADER_SIZE), ("ST_CompTableState", plc_types.STATE_SIZE),
    ("ST_CompTableLookupIn", plc_types.LOOKUP_IN_SIZE), ("ST_CompTableLookupOut", plc_types.LOOKUP_OUT_SIZE),
])
def test_struct_layouts_match_the_dut_comments_and_the_bridge(dut, size):
    t = compile_project().types[dut.lower()]
    offsets = {name: off for name, (off, _) in t.members.items()}
    assert t.size == size
    assert offsets == _comment_offsets(dut)


def test_modbus_area_layout_matches_its_register_comments():
    t = compile_project().types["st_comptablemodbusarea"]
    regs = {name: off // 2 for name, (off, _) in t.members.items()}
    assert regs == _comment_offsets("ST_CompTableModbusArea")


def test_header_bytes_round_trip_through_plc_memory():
    """Bytes packed by the bridge, read member by member by the interpreter's layout."""
    from tests.bridge_fixtures import make_table
    rt = PlcRuntime()
    header = plc_types.Header.of(make_table(version=7, n_phi=9, n_theta=5))
    rt.write_bytes("GVL_CompTable.stShadowHeader", header.pack())
    g = "GVL_CompTable.stShadowHeader"
    assert (rt.read_value(f"{g}.nTableVersion"), rt.read_value(f"{g}.aN[0]"), rt.read_value(f"{g}.aN[1]"),
            rt.read_value(f"{g}.nMotors"), rt.read_value(f"{g}.nCrc"), rt.read_value(f"{g}.aMaxStep[1]")) == (
        7, 9, 5, 2, header.crc, header.max_step[1])
    assert struct.unpack("<d", rt.read_bytes(f"{g}.aAxisMax[1]"))[0] == header.axis_max[1]


def test_unsupported_st_is_named(tmp_path):
    path = tmp_path / "bad.st"
    path.write_text("PROGRAM MAIN\nVAR\n x : INT;\nEND_VAR\nx := y;\nEND_PROGRAM\n")
    with pytest.raises(PlcCompileError, match="unknown name y"):
        compile_files([path], cache=False)


def test_the_shipped_st_uses_no_name_twincat_lacks():
    """ATAN2 is not a TwinCAT 3 operator (Infosys, Numeric operators: ABS, SQRT, LN, LOG, EXP, EXPT,
    SIN, COS, TAN, ASIN, ACOS, ATAN)."""
    prog = compile_project()
    if prog.nonstandard:
        pytest.xfail(f"today's ST calls {sorted(prog.nonstandard)} "
                     f"in {sorted(set().union(*prog.nonstandard.values()))}; the ST engineer's F_Atan2 replaces it")
    assert prog.nonstandard == {}


def test_a_function_with_in_out_arguments_runs_every_call(tmp_path):
    """Pure FUNCTIONs are evaluated once per input; a VAR_IN_OUT argument is an address whose contents
    change between calls (and may be written), so such a function runs every time."""
    src = """
FUNCTION F_Sum : UDINT
VAR_IN_OUT
    a : ARRAY[0..1] OF UDINT;
    out : UDINT;
END_VAR
F_Sum := a[0] + a[1];
out := F_Sum;
END_FUNCTION

PROGRAM MAIN
VAR
    a : ARRAY[0..1] OF UDINT;  o : UDINT;  r1, r2 : UDINT;
END_VAR
a[0] := 2; a[1] := 3;
r1 := F_Sum(a := a, out := o);
a[1] := 10;
o := 0;
r2 := F_Sum(a := a, out := o);
END_PROGRAM
"""
    rt = run_st(tmp_path, src)
    assert (rt.read_value("MAIN.r1"), rt.read_value("MAIN.r2"), rt.read_value("MAIN.o")) == (5, 12, 12)


@pytest.mark.parametrize("expression", ["r MOD 2.0", "i MOD r", "7.5 MOD 2"])
def test_mod_takes_integers_only(tmp_path, expression):
    """Infosys tc3_plc_intro, MOD (/content/1033/tc3_plc_intro/2528880779.html): permitted data types are the
    integer and bit-string types only; a REAL operand is compile error C0208 ('MOD' is not defined for 'REAL')."""
    path = tmp_path / "mod.st"
    path.write_text(f"PROGRAM MAIN\nVAR\n r : LREAL := 7.5; i : DINT := 7; x : LREAL;\nEND_VAR\nx := {expression};\n"
                    "END_PROGRAM\n")
    with pytest.raises(PlcCompileError, match="MOD takes integers only"):
        compile_files([path], cache=False)


#: two enums, the first declared strict (as plc/DUTs/E_CompTable*), the second not
ENUMS = """
{attribute 'qualified_only'}
{attribute 'strict'}
TYPE E_Strict :
(
    A := 0,
    B := 1
) INT;
END_TYPE

{attribute 'qualified_only'}
TYPE E_Loose :
(
    X := 0,
    Y := 1
) INT;
END_TYPE
"""


@pytest.mark.parametrize("strict, loose", [("e := 1;", "f := 1;"), ("e := n;", "f := n;"),
                                           ("e := E_Loose.X;", "f := E_Loose.X;"), ("n := e + 1;", "n := f + 1;"),
                                           ("e := f;", "f := g;")])
def test_a_strict_enum_takes_only_its_own_values(tmp_path, strict, loose):
    """Infosys tc3_plc_intro, Attribute 'strict' (/content/1033/tc3_plc_intro/3363142027.html): arithmetic
    with a strict enum, a constant that is not one of its values, or a value of another type assigned to
    it are compile errors in TwinCAT; the interpreter refuses them too. The same on a plain enum compiles."""
    path = tmp_path / "strict.st"
    decl = "e : E_Strict; f : E_Loose; g : E_Loose := E_Loose.Y; n : INT := 1;"
    path.write_text(ENUMS + f"PROGRAM MAIN\nVAR\n{decl}\nEND_VAR\n{strict}\nEND_PROGRAM\n")
    with pytest.raises(PlcCompileError, match="strict enum"):
        compile_files([path], cache=False)
    rt = run_st(tmp_path, ENUMS + f"PROGRAM MAIN\nVAR\n{decl}\nEND_VAR\ne := E_Strict.B;\n{loose}\nEND_PROGRAM\n")
    assert rt.read_value("MAIN.e") == 1


def test_not_complements_the_whole_x64_register_until_stored(tmp_path):
    """On x64 TwinCAT computes intermediate results in 64-bit registers and truncates them to their type only
    when they are stored (Infosys tc3_plc_intro, Operators, /content/1033/tc3_plc_intro/2528853899.html; the
    comparison case in Static Analysis SA0066, /content/1033/te1200_tc3_plcstaticanalysis/20911281419.html):
    NOT of a zero-extended UDINT or WORD has its upper bits set, so it never equals a UDINT or WORD, while the
    stored NOT, and a XOR of two values of the type, are exact. A signed value is sign-extended: NOT i = -i - 1."""
    rt = run_st(tmp_path, """
PROGRAM MAIN
VAR
    u : UDINT := 16#80000001;  c : UDINT := 16#7FFFFFFE;  s : UDINT;  w : WORD := 16#FFFF;  i : INT := 5;
    bEq, bXor, bWord, bStored, bInt : BOOL;
END_VAR
s := NOT u;
bEq := c = NOT u;
bXor := (c XOR u) = 16#FFFFFFFF;
bWord := NOT w = 0;
bStored := c = s;
bInt := NOT i = -6;
END_PROGRAM
""")
    v = {k: rt.read_value(f"MAIN.{k}") for k in ("s", "bEq", "bXor", "bWord", "bStored", "bInt")}
    assert v == dict(s=0x7FFFFFFE, bEq=False, bXor=True, bWord=False, bStored=True, bInt=True)


@pytest.mark.parametrize("pack, size", [("0", 8), ("1", 8), ("2", 10), ("4", 12), ("8", 12)])
def test_pack_mode_sizes_of_the_infosys_sample(tmp_path, pack, size):
    """Infosys' pack_mode sample (CX7000 Attribute 'pack_mode', /content/1033/cx7000/10697920651.html, and
    tc3_plc_intro /content/1033/tc3_plc_intro/2529746059.html): BYTE, DINT, BYTE, INT gives SIZEOF 8 with
    pack mode 0 (no gaps, as 1), 10 with 2, 12 with 4 and 8."""
    rt = run_st(tmp_path, f"""
{{attribute 'pack_mode' := '{pack}'}}
TYPE str_Test :
STRUCT
    byTest1 : BYTE;
    iTest   : DINT;
    byTest2 : BYTE;
    nValue  : INT;
END_STRUCT
END_TYPE

PROGRAM MAIN
VAR
    st : str_Test;  n : UDINT;
END_VAR
n := SIZEOF(st);
END_PROGRAM
""")
    assert rt.read_value("MAIN.n") == size


#: a function block and a program whose members other POUs write (MAIN)
OWNERS = """
FUNCTION_BLOCK FB_Owner
VAR_INPUT
    bIn : BOOL;
END_VAR
VAR_OUTPUT
    bOut : BOOL;
END_VAR
VAR
    bLocal : BOOL;
END_VAR
bOut := bIn;
END_FUNCTION_BLOCK

PROGRAM PRG_Owner
VAR_INPUT
    bIn : BOOL;
END_VAR
VAR
    bLocal : BOOL;
    fb : FB_Owner;
END_VAR
END_PROGRAM
"""


@pytest.mark.parametrize("statement, allowed", [
    ("fb.bIn := TRUE;", True), ("PRG_Owner.bIn := TRUE;", True), ("PRG_Owner.fb.bIn := TRUE;", True),
    ("fb.bLocal := TRUE;", False), ("fb.bOut := TRUE;", False), ("PRG_Owner.bLocal := TRUE;", False),
    ("GVL.gFb.bLocal := TRUE;", False), ("GVL.gFb.bIn := TRUE;", True)])
def test_only_inputs_are_written_from_outside(tmp_path, statement, allowed):
    """TwinCAT reports a write from outside to a program's or function block's own variable (VAR, VAR_OUTPUT)
    as a compile error; inputs may be written (Infosys Static Analysis SA0102,
    /content/1033/te1200_tc3_plcstaticanalysis/20911240331.html)."""
    path = tmp_path / "access.st"
    path.write_text(OWNERS + "{attribute 'qualified_only'}\nVAR_GLOBAL\n    gFb : FB_Owner;\nEND_VAR\n"
                    f"PROGRAM MAIN\nVAR\n    fb : FB_Owner;\nEND_VAR\n{statement}\nEND_PROGRAM\n")
    if allowed:
        compile_files([path], cache=False)
    else:
        with pytest.raises(PlcCompileError, match="written from outside"):
            compile_files([path], cache=False)
