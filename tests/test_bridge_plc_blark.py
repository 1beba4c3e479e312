"""Every ST file of plc/ parses with blark (an independent IEC 61131-3 / TwinCAT parser), and the
declarations blark reads back agree with bridge/plc_types.py: struct member types and byte offsets,
enum-free constants, and the nominal-IK reference geometry."""

from __future__ import annotations

import functools
import re
from pathlib import Path

import pytest

blark_parse = pytest.importorskip("blark.parse")
from blark.summary import CodeSummary  # noqa: E402

from pmcal.bridge import plc_types  # noqa: E402
from pmcal.bridge.comptable import FORMAT_VERSION, NAXES_MAX, NMOTOR_MAX, NVALUES_MAX  # noqa: E402
from pmcal.bridge.modbus_map import ModbusMap  # noqa: E402
from pmcal.bridge.nominal import NominalReference  # noqa: E402

PLC = Path(__file__).resolve().parent.parent / "plc"
FILES = sorted(p for p in PLC.rglob("*") if p.suffix in (".TcPOU", ".TcDUT", ".TcGVL"))
SIZES = {"LREAL": 8, "UDINT": 4, "DWORD": 4, "DINT": 4, "UINT": 2, "INT": 2, "WORD": 2, "BYTE": 1, "BOOL": 1}


@functools.lru_cache(maxsize=None)
def _parsed(path: Path) -> tuple:
    return tuple(blark_parse.parse(path))


@pytest.fixture(scope="module")
def summary():
    return CodeSummary.from_parse_results([r for f in FILES for r in _parsed(f)])


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_every_st_file_parses(path):
    results = _parsed(path)
    assert results and all(r.exception is None for r in results), [str(r.exception) for r in results]


def _consts(summary) -> dict[str, str]:
    return {str(k): str(v.value) for k, v in summary.globals["GVL_CompTableParam"].declarations.items()}


def _size(summary, type_name: str) -> int:
    t = type_name.replace(" ", "")
    if t in SIZES:
        return SIZES[t]
    if m := re.fullmatch(r"STRING\((\d+)\)", t):
        return int(m[1]) + 1
    if t.startswith("E_"):
        return 2
    if m := re.fullmatch(r"ARRAY\[(.*?)\]OF(.+)", t):
        consts = _consts(summary)
        n = 1
        for rng in m[1].split(","):
            lo, hi = (eval(re.sub(r"GVL_CompTableParam\.(\w+)", lambda g: consts[g[1]], x), {})  # noqa: S307
                      for x in rng.split(".."))
            n *= hi - lo + 1
        return n * _size(summary, m[2])
    return sum(_size(summary, str(d.type)) for d in summary.data_types[t].declarations.values())


def _layout(summary, struct: str) -> list[tuple[str, int, int]]:
    out, at = [], 0
    for name, decl in summary.data_types[struct].declarations.items():
        size = _size(summary, str(decl.type))
        out.append((str(name), at, size))
        at += size
    return out


@pytest.mark.parametrize("struct, size", [
    ("ST_CompTableHeader", plc_types.HEADER_SIZE), ("ST_CompTableState", plc_types.STATE_SIZE),
    ("ST_CompTableLookupIn", plc_types.LOOKUP_IN_SIZE), ("ST_CompTableLookupOut", plc_types.LOOKUP_OUT_SIZE),
])
def test_struct_sizes_match_the_bridge(summary, struct, size):
    assert sum(s for _, _, s in _layout(summary, struct)) == size


def test_header_and_state_offsets_match_the_packed_formats(summary):
    """Offsets from blark's declarations against the struct formats the bridge packs with."""
    import struct as st

    fmt = plc_types._HEADER.format.lstrip("<")
    header = {n: off for n, off, _ in _layout(summary, "ST_CompTableHeader")}
    assert header["aMotorMin"] == st.calcsize("<6d") and header["nTableVersion"] == st.calcsize("<24d")
    assert header["nAxes"] == st.calcsize("<24dIH") and header["nMotors"] == st.calcsize("<24dI5H")
    assert header["nReference"] == st.calcsize("<24dI6H") and header["nCrc"] == st.calcsize("<24dI8H")
    assert header["nReferenceCrc"] == header["nCrc"] + 4 and header["sMachine"] == st.calcsize("<24dI8H2I")
    assert st.calcsize("<" + fmt) == plc_types.HEADER_SIZE
    state = {n: off for n, off, _ in _layout(summary, "ST_CompTableState")}
    assert state["nActiveCrc"] == st.calcsize("<3I2H") and state["nStagingOwner"] == st.calcsize("<3I2HI")


def test_modbus_area_offsets_match_the_register_map(summary):
    rmap = ModbusMap()
    regs = {n: off // 2 for n, off, _ in _layout(summary, "ST_CompTableModbusArea")}
    assert (regs["stShadowHeader"], regs["nCommitToken"], regs["stState"], regs["stActiveHeader"],
            regs["stLookupIn"], regs["stLookupOut"], regs["nStagingClaim"], regs["aWindow"]) == (
        rmap.SHADOW_HEADER, rmap.COMMIT_VERSION, rmap.STATE, rmap.ACTIVE_HEADER, rmap.LOOKUP_IN,
        rmap.LOOKUP_OUT, rmap.STAGING_CLAIM, rmap.WINDOW)


def test_constants_match_the_bridge(summary):
    c = _consts(summary)
    assert (int(c["NAXES_MAX"]), int(c["NMOTOR_MAX"]), int(c["NVALUES_MAX"])) == (NAXES_MAX, NMOTOR_MAX, NVALUES_MAX)
    assert (int(c["INTERFACE_VERSION"]), int(c["FORMAT_VERSION"])) == (plc_types.INTERFACE_VERSION, FORMAT_VERSION)
    ref = NominalReference.default()
    assert tuple(float(c[k]) for k in ("REF_A_MM", "REF_H_MM", "REF_L_MM", "REF_PSI1_DEG", "REF_PSI2_DEG")) == (
        ref.a_mm, ref.h_mm, ref.l_mm, ref.psi1_deg, ref.psi2_deg)


def test_nominal_ik_function_declares_what_the_lookup_calls(summary):
    f = summary.functions["F_CompTableNominalIk"]
    names = {str(k) for k in f.declarations}
    assert {"fPhi", "fTheta", "fM1", "fM2"} <= names
