"""The PLC side: the ST of plc/ run by the interpreter (bridge.plc_runtime), and the ST sources agreeing
with the bridge.

The interpreted PLC is exercised directly here, without a network; the transport suites run it
behind real ADS and Modbus servers.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from pmcal.bridge.comptable import FORMAT_VERSION, NAXES_MAX, NMOTOR_MAX, NVALUES_MAX, crc32
from pmcal.bridge import plc_types
from pmcal.bridge.modbus_map import MAGIC, PAGE_LOAD, PAGE_STORE, ModbusMap
from pmcal.bridge.nominal import NominalReference
from pmcal.bridge.simulator.plc_runtime import PlcTwin
from pmcal.bridge.plc_types import (SYMBOLS, Header, LookupIn, LookupOut, LookupResult, State, Status,
                              done_value, shadow_rows)
from tests.bridge_fixtures import make_table

PLC = Path(__file__).resolve().parent.parent / "plc"


# ---- the twin of FB_CompTableManager / FB_CompTableCheck / FB_CompTableLookup ----------------

#: the staging token of the tests' client
TOKEN = 0xDEED0001


def stage(twin: PlcTwin, table, header: Header | None = None) -> None:
    """Claim the staging area with TOKEN (granted in one cycle) and stage ``table``."""
    twin.write_symbol("staging_claim", TOKEN.to_bytes(4, "little"))
    twin.cycle()
    assert twin.state.staging_owner == TOKEN
    twin.write_symbol("shadow_header", (header or Header.of(table)).pack())
    twin.write_symbol("shadow", shadow_rows(table) + bytes(plc_types.SHADOW_SIZE - len(shadow_rows(table))))


def commit(twin: PlcTwin, token: int = TOKEN, cycles: int = 3):
    """Write nCommitToken and run the task: one cycle, the cycles the snapshot and FB_CompTableCheck
    need (spread over cycles by their budget), then ``cycles - 2`` more."""
    twin.write_symbol("commit", token.to_bytes(4, "little"))
    twin.cycle()
    if cycles > 1:
        for _ in range(100_000):
            if twin.state.state != State.CHECKING:
                break
            assert twin.cycle(), twin.fault
        for _ in range(cycles - 2):
            twin.cycle()
    return twin.state


def test_commit_swaps_only_when_motion_allows_and_acknowledges_last():
    twin = PlcTwin()
    table = make_table(version=1)
    stage(twin, table)
    twin.motion_idle = False
    st = commit(twin)
    assert (st.state, st.status, st.ack_token, st.active_version) == (State.WAIT_MOTION, Status.BUSY, 0, 0)
    twin.motion_idle = True
    for _ in range(200):                   # the swap, then the save in PersistTask (every 10 cycles), then the ack
        twin.cycle()
        if twin.state.ack_token:
            break
    st = twin.state
    assert (st.state, st.status, st.ack_token, st.active_version, st.active_crc) == (
        State.IDLE, Status.OK, TOKEN, 1, table.crc32())
    header, values = twin.active_table()
    assert header == Header.of(table) and values.tobytes() == table.values.tobytes()
    st = commit(twin, done_value(TOKEN), cycles=1)                         # release: ack cleared, table stays
    assert (st.ack_token, st.active_version) == (0, 1)


def test_snapshot_at_commit_ignores_later_writes_to_staging():
    twin = PlcTwin()
    table = make_table(version=1)
    stage(twin, table)
    twin.motion_idle = False
    commit(twin)
    stage(twin, make_table(version=1, offset_deg=1.0))     # staging overwritten while waiting
    twin.motion_idle = True
    for _ in range(20):
        twin.cycle()
    assert twin.active_table()[1].tobytes() == table.values.tobytes()


def _bad(kind: str):
    """(table, header) for a rejected commit of version 2 on a PLC whose active version is 1."""
    table = make_table(version=2, n_phi=9, n_theta=5)
    h = Header.of(table)
    if kind == "format":
        h = replace(h, format_version=FORMAT_VERSION + 1)
    elif kind == "stale":
        h = Header.of(make_table(version=1, n_phi=9, n_theta=5))
    elif kind == "grid_size":
        h = replace(h, n=(NVALUES_MAX // 2 + 1, 2))
    elif kind == "grid_limits":
        h = replace(h, axis_max=(h.axis_max[0], -1.0))
    elif kind == "limits":
        h = replace(h, max_step=(h.max_step[0], float("nan")))
    elif kind == "crc":
        h = replace(h, crc=h.crc ^ 0x0100)
    else:
        table.values[4, 2, 1] = {"nan": np.nan, "range": 80.0 - table.nominal_at_nodes()[4, 2, 1],
                                 "step": table.values[4, 2, 1] + 20.0}[kind]
        h = Header.of(table)
    return table, h


@pytest.mark.parametrize("kind, status", [
    ("format", Status.FORMAT_VERSION), ("stale", Status.STALE_VERSION), ("grid_size", Status.GRID_SIZE),
    ("grid_limits", Status.GRID_LIMITS),
    ("limits", Status.LIMITS),
    ("crc", Status.CRC_MISMATCH),
    ("nan", Status.NOT_FINITE), ("range", Status.OUT_OF_RANGE), ("step", Status.STEP_TOO_LARGE),
])
def test_rejections_leave_the_active_table(kind, status):
    twin = PlcTwin()
    good = make_table(version=1)
    twin.seed(good)
    table, header = _bad(kind)
    stage(twin, table, header)
    st = commit(twin)
    assert (st.status, st.ack_token, st.active_version, st.active_crc) == (status, TOKEN, 1, good.crc32())
    assert not twin.stopped
    assert twin.active_table()[1].tobytes() == good.values.tobytes()


def test_version_zero_is_refused():
    twin = PlcTwin()
    table = make_table(version=5)
    stage(twin, table, replace(Header.of(table), table_version=0))
    assert commit(twin).status == Status.VERSION_MISMATCH


def test_a_commit_with_another_token_than_the_owners_is_ignored():
    """Fencing: a client that lost the staging area (its lease ended) cannot commit over the owner."""
    twin = PlcTwin()
    stage(twin, make_table(version=5))
    st = commit(twin, TOKEN + 2)                           # a stale client's token
    assert (st.state, st.ack_token, st.active_version, st.status) == (State.IDLE, 0, 0, Status.NONE)
    assert commit(twin, TOKEN, cycles=30).active_version == 5


def test_withdrawal_and_swap_timeout_leave_the_active_table():
    twin = PlcTwin(commit_timeout_s=0.0)
    twin.seed(make_table(version=1))
    stage(twin, make_table(version=2))
    twin.motion_idle = False
    st = commit(twin)
    assert (st.status, st.ack_token, st.active_version) == (Status.SWAP_TIMEOUT, TOKEN, 1)
    twin = PlcTwin()
    twin.seed(make_table(version=1))
    stage(twin, make_table(version=2))
    twin.motion_idle = False
    commit(twin)
    st = commit(twin, done_value(TOKEN), cycles=1)
    assert (st.status, st.ack_token, st.active_version) == (Status.WITHDRAWN, TOKEN, 1)


def test_lookup_is_bit_identical_to_the_python_interpolation():
    twin = PlcTwin()
    assert _lookup(twin, 10.0, 10.0).result == LookupResult.NO_TABLE
    table = make_table(version=3, n_phi=100, n_theta=100)
    twin.seed(table)
    rng = np.random.default_rng(2)
    phi, theta = rng.uniform(0, 360, 200), rng.uniform(0, 60, 200)
    phi[:2], theta[:2] = (0.0, 360.0), (0.0, 60.0)            # grid corners
    ref = table.interpolate(phi, theta)
    for k in range(len(phi)):
        out = _lookup(twin, phi[k], theta[k])
        assert (out.result, out.table_version) == (LookupResult.OK, 3)
        assert (out.m1_deg, out.m2_deg) == (ref[k, 0], ref[k, 1])
    assert _lookup(twin, 10.0, 60.5).result == LookupResult.OUT_OF_GRID


def test_a_nan_target_is_out_of_grid_and_the_task_runs_on():
    twin = PlcTwin()
    twin.seed(make_table(version=3))
    assert _lookup(twin, float("nan"), 10.0).result == LookupResult.OUT_OF_GRID
    assert not twin.stopped


def _lookup(twin: PlcTwin, phi: float, theta: float) -> LookupOut:
    seq = LookupOut.unpack(twin.read_symbol("lookup_out")).seq + 1
    twin.write_symbol("lookup_in", LookupIn((phi, theta), seq).pack())
    twin.cycle()
    out = LookupOut.unpack(twin.read_symbol("lookup_out"))
    assert out.seq == seq
    return out


def test_plc_owned_symbols_cannot_be_written():
    with pytest.raises(PermissionError):
        PlcTwin().write_symbol("state", bytes(plc_types.STATE_SIZE))


# ---- the ST sources ------------------------------------------------------------------------

def _declarations() -> dict[str, str]:
    """Name -> declaration text of every DUT, GVL and POU under plc/ (the files must be valid XML)."""
    out = {}
    for path in sorted(PLC.rglob("*.Tc*")):
        root = ET.parse(path).getroot()
        assert root.tag == "TcPlcObject"
        obj = root[0]
        assert obj.get("Name") == path.stem and re.fullmatch(r"\{[0-9a-f-]{36}\}", obj.get("Id"))
        if path.suffix != ".TcTTO":                       # a task object has no declaration
            out[path.stem] = obj.find("Declaration").text
    return out


DECL = _declarations()
_SIZES = {"LREAL": 8, "UDINT": 4, "DWORD": 4, "UINT": 2, "WORD": 2, "INT": 2, "BYTE": 1, "BOOL": 1}


def _constants() -> dict[str, object]:
    consts = {}
    pattern = r"^\s*(\w+)\s*:\s*\w+(?:\(\d+\))?\s*:=\s*([^;]+);"
    for name, value in re.findall(pattern, DECL["GVL_CompTableParam"], re.M):
        value = value.strip()
        consts[name] = (int(value[3:], 16) if value.startswith("16#") else value.strip("'") if value.startswith("'")
                        else value if value.startswith("T#")
                        else value == "TRUE" if value in ("TRUE", "FALSE")
                        else float(value) if "." in value or "E" in value else int(value))
    return consts


CONST = _constants()


def _resolve(text: str) -> str:
    text = re.sub(r"GVL_CompTableParam\.(\w+)", lambda m: str(CONST[m[1]]), text)
    return re.sub(r"(\d+)\s*-\s*(\d+)", lambda m: str(int(m[1]) - int(m[2])), text)


def _members(decl: str) -> list[tuple[str, str]]:
    body = re.search(r"\b(?:STRUCT|VAR_GLOBAL)\b(.*?)\bEND_(?:STRUCT|VAR)\b", decl, re.S)[1]
    body = re.sub(r"//[^\n]*", "", body)
    out, hidden = [], False
    for line in body.splitlines():
        if "{attribute 'hide'}" in line:
            hidden = True
            continue
        m = re.match(r"\s*(\w+)\s*(?:AT\s+%\w+\s*)?:\s*([^:;]+?)\s*(?::=[^;]*)?;", line)
        if m:
            if not hidden:
                out.append((m[1], _resolve(m[2])))
            hidden = False
    return out


def _size(type_: str) -> int:
    type_ = type_.strip()
    if type_ in _SIZES:
        return _SIZES[type_]
    if m := re.fullmatch(r"STRING\((\d+)\)", type_):
        return int(m[1]) + 1
    if type_.startswith("E_"):
        return 2                                            # enums with base type INT
    if m := re.fullmatch(r"ARRAY\s*\[(.*?)\]\s*OF\s+(.+)", type_):
        n = 1
        for rng in m[1].split(","):
            lo, hi = (int(x) for x in rng.split(".."))
            n *= hi - lo + 1
        return n * _size(m[2])
    return sum(_size(t) for _, t in _members(DECL[type_]))


def _offsets(struct: str) -> dict[str, int]:
    out, at = {}, 0
    for name, t in _members(DECL[struct]):
        out[name] = at
        at += _size(t)
    return out


def _enum(name: str) -> dict[str, int]:
    return {k: int(v) for k, v in re.findall(r"(\w+)\s*:=\s*(\d+)", DECL[name])}


def test_st_enums_match_the_bridge():
    assert _enum("E_CompTableStatus") == {s.name: s.value for s in Status}
    assert _enum("E_CompTableState") == {s.name: s.value for s in State}
    assert _enum("E_CompTableLookup") == {s.name: s.value for s in LookupResult}


def test_st_constants_match_the_bridge():
    rmap = ModbusMap()
    assert (CONST["NAXES_MAX"], CONST["NMOTOR_MAX"], CONST["NVALUES_MAX"]) == (NAXES_MAX, NMOTOR_MAX, NVALUES_MAX)
    assert (CONST["INTERFACE_VERSION"], CONST["FORMAT_VERSION"]) == (plc_types.INTERFACE_VERSION, FORMAT_VERSION)
    assert (CONST["WINDOW_LREALS"], CONST["MB_MAGIC"]) == (rmap.window_lreals, MAGIC)
    assert (CONST["PAGE_STORE"], CONST["PAGE_LOAD"]) == (PAGE_STORE, PAGE_LOAD)
    assert crc32(CONST["CRC_TEST_VECTOR"].encode()) == CONST["CRC_TEST_RESULT"] == 0xCBF43926
    # the nominal-IK reference the PLC computes is the one tables are written against
    ref = NominalReference.default()
    assert tuple(float(CONST[k]) for k in ("REF_A_MM", "REF_H_MM", "REF_L_MM", "REF_PSI1_DEG", "REF_PSI2_DEG")) == (
        ref.a_mm, ref.h_mm, ref.l_mm, ref.psi1_deg, ref.psi2_deg)


def test_st_structs_have_the_bridge_byte_layout():
    assert _size("ST_CompTableHeader") == plc_types.HEADER_SIZE == 248
    assert _size("ST_CompTableState") == plc_types.STATE_SIZE == 24
    assert _size("ST_CompTableLookupIn") == plc_types.LOOKUP_IN_SIZE == 32
    assert _size("ST_CompTableLookupOut") == plc_types.LOOKUP_OUT_SIZE == 64
    h = _offsets("ST_CompTableHeader")
    assert (h["aMotorMin"], h["nTableVersion"], h["nAxes"], h["aN"], h["nMotors"], h["nReference"], h["nPrismatic"],
            h["nCrc"], h["nReferenceCrc"], h["sMachine"]) == (48, 192, 198, 200, 206, 208, 210, 212, 216, 220)
    st = _offsets("ST_CompTableState")
    assert (st["nAckToken"], st["eStatus"], st["eState"], st["nActiveCrc"], st["nStagingOwner"]) == (0, 12, 14, 16, 20)
    packed = Header.of(make_table(version=0x01020304)).pack()
    assert packed[192:196] == bytes([4, 3, 2, 1]) and Header.unpack(packed).table_version == 0x01020304


#: two DUTs without pack_mode (TwinCAT 3's default, 8): an inner struct of alignment 4 and size 8 (5 bytes of
#: members, 3 of tail padding), an outer one around it
_NATURAL_DUTS = {
    "ST_Inner": "TYPE ST_Inner :\nSTRUCT\n\tn : DINT;\n\tb : BYTE;\nEND_STRUCT\nEND_TYPE\n",
    "ST_Outer": "TYPE ST_Outer :\nSTRUCT\n\ta : BYTE;\n\tst : ST_Inner;\n\tc : BYTE;\n\tf : LREAL;\n"
                "\tw : ARRAY[0..1] OF ST_Inner;\nEND_STRUCT\nEND_TYPE\n",
}


def test_struct_members_follow_natural_alignment(monkeypatch):
    """Struct members the ADS mock serves by name (``GVL.st.member``) lie where TwinCAT 3 puts them (Infosys
    tc3_plc_intro, Alignment, /content/1033/tc3_plc_intro/3539428491.html): a struct sits at a multiple of
    its largest member (ST_Inner: 4) and takes a multiple of it (8, not 5), worked out by hand:
    a 0, st 4 (st.n 4, st.b 8), c 12, f 16, w 24 (w[1] at 32), size 40. The shipped DUTs are pack_mode 1."""
    from pmcal.bridge import ads_map

    monkeypatch.setattr(ads_map, "_dut_text", _NATURAL_DUTS.get)
    m = ads_map.struct_members("ST_Outer")
    assert {k: v[0] for k, v in m.items()} == {"a": 0, "st": 4, "st.n": 4, "st.b": 8, "c": 12, "f": 16, "w": 24}
    assert (m["st"][1], m["w"][1]) == (8, 16)


def test_st_modbus_area_matches_the_register_map():
    rmap = ModbusMap()
    off = {k: v // 2 for k, v in _offsets("ST_CompTableModbusArea").items()}
    assert (off["nMagic"], off["stShadowHeader"], off["nCommitToken"], off["nPageIndex"], off["nPageSeqDone"],
            off["stState"], off["stActiveHeader"], off["stLookupIn"], off["stLookupOut"], off["aWindow"]) == (
        rmap.MAGIC, rmap.SHADOW_HEADER, rmap.COMMIT_VERSION, rmap.PAGE_CONTROL, rmap.PAGE_ACK,
        rmap.STATE, rmap.ACTIVE_HEADER, rmap.LOOKUP_IN, rmap.LOOKUP_OUT, rmap.WINDOW)
    assert _size("ST_CompTableModbusArea") // 2 <= rmap.area_size == 12288


def test_gvl_exposes_exactly_the_bridge_symbols():
    declared = _members(DECL["GVL_CompTable"])
    assert [(n, t.replace(" ", "")) for n, t in declared] == [
        (s.st_name, s.st_type.replace(" ", "")) for s in SYMBOLS]
    assert all(_size(t) == s.size for (_, t), s in zip(declared, SYMBOLS))
