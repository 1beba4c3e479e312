"""Hostile tables and targets against the shipped ST (plc/, run by bridge.plc_runtime): whatever a
client stages, whatever sits in persistent memory, whatever target a lookup asks for, the PLC task
never stops (TwinCAT stops it on a NaN produced or compared and on a division by zero), and a table
that is not valid never becomes active.

Tables of corrections to the controller's own IK (nReference = 2) get the same treatment, and each
refusal is checked against the status code that names it and against CompTable.defect.

Three paths of the ST: the commit check (FB_CompTableManager + FB_CompTableCheck on a staged table),
the start-up check (the same on the persistent table after a restart), and the lookup
(FB_CompTableLookup answering stLookupIn). Every case runs on the shipped ST without an expected failure."""

from __future__ import annotations

import math
import zlib
from dataclasses import replace

import numpy as np
import pytest

from pmcal.bridge import plc_types
from pmcal.bridge.comptable import CORRECTION_ABS_MAX, Axis, CompTable, Motor
from pmcal.bridge.simulator.plc_runtime import PlcTwin
from pmcal.bridge.plc_types import Header, LookupIn, LookupOut, LookupResult, State, Status, shadow_rows
from tests.bridge_fixtures import INTERFACE_COPIES, make_table

#: values no table should hold, and what a PLC must survive reading
HOSTILE = {"nan": math.nan, "+inf": math.inf, "-inf": -math.inf, "huge": 1e308, "-huge": -1e308,
           "denormal": 5e-324, "-zero": -0.0}
#: cycles a commit may take on a small table before the test calls it stuck
MAX_CYCLES = 20_000

#: the staging token of the tests' client
TOKEN = 0x8BAD7AB1


def _small(version: int = 2, **kw):
    return make_table(version=version, n_phi=37, n_theta=13, **kw)     # a valid table (9x5 steps too far)


def _plc(like: CompTable | None = None) -> PlcTwin:
    """A PLC configured for the machine, motors and kind of ``like`` (default: the OCPM's table), with
    version 1 of that table active."""
    like = like or _small(version=1)
    plc = PlcTwin(machine=like.machine, motors=like.n_motors,
                  corrections=like.reference_code == plc_types.REFERENCE_CONTROLLER)
    plc.seed(replace(like, version=1))
    return plc


def _commit(plc: PlcTwin, header: Header, values: np.ndarray | None = None, table=None):
    """Stage ``header`` (and the table's rows, or raw ``values`` of shape (n_phi, n_theta, 2)), commit
    its version, run until the manager acknowledges it (or the task stops)."""
    table = table or _small()
    rows = shadow_rows(table) if values is None else _rows(values)
    plc.write_symbol("staging_claim", TOKEN.to_bytes(4, "little"))
    plc.write_symbol("shadow_header", header.pack())
    plc.write_symbol("shadow", rows + bytes(plc_types.SHADOW_SIZE - len(rows)))
    plc.cycle()                                           # the claim is granted
    plc.write_symbol("commit", TOKEN.to_bytes(4, "little"))
    for _ in range(MAX_CYCLES):
        if not plc.cycle():
            break
        st = plc.state
        if st.ack_token == TOKEN and st.state == State.IDLE:
            break
    return plc.state


def _rows(values: np.ndarray) -> bytes:
    return np.ascontiguousarray(values, dtype="<f8").tobytes()      # flat, C order (ST_CompTableHeader)


def _assert_survived_and_refused(plc: PlcTwin, st) -> None:
    assert not plc.stopped, plc.fault
    assert isinstance(st.status, Status) and st.status.is_rejection, st
    assert st.active_version == 1


def _set(t: tuple, k: int, v) -> tuple:
    return t[:k] + (v,) + t[k + 1:]


def _header_cases():
    t = _small()
    h = Header.of(t)
    cases = []
    for field in ("axis_min", "axis_max", "motor_min", "motor_max", "max_step"):
        for k in (0, 1):
            for name, v in HOSTILE.items():
                if name in ("denormal", "-zero") and field != "max_step":
                    continue
                cases.append(pytest.param(replace(h, **{field: _set(getattr(h, field), k, v)}),
                                          id=f"{field}[{k}]={name}"))
    cases += [
        pytest.param(replace(h, max_step=(h.max_step[0], 0.0)), id="max_step=0"),
        pytest.param(replace(h, max_step=(-1.0, h.max_step[1])), id="max_step<0"),
        pytest.param(replace(h, axis_min=(h.axis_max[0], 0.0), axis_max=(h.axis_min[0], 60.0)), id="phi reversed"),
        pytest.param(replace(h, axis_min=(-400.0, 0.0)), id="phi span>360"),
        pytest.param(replace(h, motor_min=h.motor_max, motor_max=h.motor_min), id="motor limits reversed"),
        pytest.param(replace(h, n=(0, 13)), id="n_phi=0"), pytest.param(replace(h, n=(1, 13)), id="n_phi=1"),
        pytest.param(replace(h, n=(37, 1)), id="n_theta=1"),
        pytest.param(replace(h, n=(10001, 2)), id="values beyond NVALUES_MAX"),
        pytest.param(replace(h, n=(65535, 65535)), id="n=65535x65535 (product overflows UDINT)"),
        pytest.param(replace(h, n=(37, 13, 65535), axis_min=(0.0, 0.0, 0.0), axis_max=(360.0, 60.0, 1.0),
                             n_axes=3), id="third axis overflowing"),
        pytest.param(replace(h, n=(37, 4)), id="n_theta smaller than the data"),
        pytest.param(replace(h, n_axes=0), id="nAxes=0"), pytest.param(replace(h, n_axes=4), id="nAxes=4"),
        pytest.param(replace(h, n_axes=65535), id="nAxes=65535"),
        pytest.param(replace(h, n_axes=1), id="nAxes=1 with the reference"),
        pytest.param(replace(h, n_motors=0), id="nMotors=0"), pytest.param(replace(h, n_motors=7), id="nMotors=7"),
        pytest.param(replace(h, n_motors=65535), id="nMotors=65535"),
        pytest.param(replace(h, n_motors=3, motor_min=h.motor_min + (-1.0,), motor_max=h.motor_max + (1.0,),
                             max_step=h.max_step + (1.0,)), id="nMotors=3 with the reference"),
        pytest.param(replace(h, prismatic=1), id="prismatic motor with the reference"),
        pytest.param(replace(h, reference=7), id="reference=7"),
        pytest.param(replace(h, reference_crc=h.reference_crc ^ 1), id="reference crc"),
        pytest.param(replace(h, axis_max=(360.0, 170.0)), id="theta beyond reach"),
        pytest.param(replace(h, machine="another_machine"), id="machine renamed (MACHINE_MISMATCH)"),
    ]
    return cases


@pytest.mark.parametrize("header", _header_cases())
def test_hostile_header_is_refused_and_the_task_runs_on(header):
    plc = _plc()
    _assert_survived_and_refused(plc, _commit(plc, header))


def _value_cases():
    cases = []
    for reference in ("nominal_ik", None):
        for name, v in HOSTILE.items():
            if name in ("denormal", "-zero"):
                continue                      # valid values: see the acceptance test below
            cases.append(pytest.param(reference, v, id=f"{reference or 'absolute'}:{name}"))
    return cases


@pytest.mark.parametrize("reference, value", _value_cases())
def test_hostile_value_is_refused_and_the_task_runs_on(reference, value):
    table = _small(reference=reference)
    values = table.values.copy()
    values[4, 2, 1] = value
    header = _with_crc(Header.of(table), values)        # a CRC that matches: the values are checked
    plc = _plc()
    _assert_survived_and_refused(plc, _commit(plc, header, values=values, table=table))


def test_denormal_and_negative_zero_values_are_accepted():
    """5e-324 and -0.0 are finite, in range and steady: a valid table."""
    table = _small()
    values = table.values.copy()
    values[4, 2, 1] = values[4, 2, 1] + 5e-324
    values[0, 0, 0] = -0.0 if values[0, 0, 0] == 0.0 else values[0, 0, 0]
    plc = _plc(table)
    st = _commit(plc, _with_crc(Header.of(table), values), values=values, table=table)
    assert not plc.stopped and (st.status, st.active_version) == (Status.OK, 2)


def _with_crc(header: Header, values: np.ndarray) -> Header:
    """``header`` with the CRC-32 that matches it and ``values`` (header image with nCrc = 0, then the rows)."""
    data = np.ascontiguousarray(values, dtype="<f8").tobytes()
    return replace(header, crc=zlib.crc32(data, zlib.crc32(replace(header, crc=0).pack())))


# ---- the start-up check on a hostile persistent table -------------------------------------------

@pytest.mark.parametrize("value", [pytest.param(v, id=k) for k, v in HOSTILE.items() if k not in ("denormal", "-zero")])
def test_hostile_persistent_table_is_dropped_at_start_up(value):
    table = make_table(version=3, n_phi=37, n_theta=13, reference=None)
    plc = PlcTwin()
    plc.seed(table)
    rt = plc.runtime
    k = rt.read_value("GVL_CompTableStore.nActive")
    addr, _ = rt.locate(f"GVL_CompTableStore.aBuffer[{k}][{(4 * 13 + 2) * 2 + 1}]")
    rt.mem[addr:addr + 8] = np.float64(value).tobytes()            # persistent memory damaged
    values = table.values.copy()
    values[4, 2, 1] = value
    hdr = _with_crc(Header.of(table), values)            # ... with a matching CRC
    rt.write_bytes(f"GVL_CompTableStore.aHeader[{k}]", hdr.pack())
    rt.restart()
    for _ in range(MAX_CYCLES):
        if not plc.cycle() or plc.started:
            break
    assert not plc.stopped, plc.fault
    st = plc.state
    assert st.active_version == 0 and st.status.is_rejection


# ---- the lookup ------------------------------------------------------------------------------------

def _lookup(plc: PlcTwin, phi: float, theta: float) -> LookupOut:
    seq = LookupOut.unpack(plc.read_symbol("lookup_out")).seq + 1
    plc.write_symbol("lookup_in", LookupIn((phi, theta), seq).pack())
    plc.cycle()
    return LookupOut.unpack(plc.read_symbol("lookup_out"))


@pytest.mark.parametrize("phi, theta", [
    pytest.param(v, 10.0, id=f"phi={k}") for k, v in HOSTILE.items()] + [
    pytest.param(10.0, v, id=f"theta={k}") for k, v in HOSTILE.items()])
def test_hostile_target_never_stops_the_task(phi, theta):
    plc = _plc()
    out = _lookup(plc, phi, theta)
    assert not plc.stopped, plc.fault
    inside = 0.0 <= phi <= 360.0 and 0.0 <= theta <= 60.0
    assert out.result == (LookupResult.OK if inside else LookupResult.OUT_OF_GRID)
    assert not out.correction                       # an nReference = 1 table answers commands
    if not inside:
        assert (out.m1_deg, out.m2_deg) == (0.0, 0.0)


# ---- tables of corrections to the controller's own IK (nReference = 2) ---------------------------

#: a correction table over 3 axes of 2 revolute motors and 1 prismatic: bounds +-0.5, steps <= 0.2
CORR_AXES = [Axis("x", "mm", -50.0, 70.0, 6), Axis("y", "mm", -30.0, 40.0, 5), Axis("z", "mm", -900.0, -700.0, 3)]
CORR_MOTORS = [Motor("m1", "deg", -0.5, 0.5, 0.2), Motor("m2", "deg", -0.5, 0.5, 0.2),
               Motor("m3", "mm", -0.5, 0.5, 0.2)]


def corrections(version: int = 2, scale: float = 1.0) -> CompTable:
    """A valid correction table (nReference = 2): a smooth field of at most 0.3 deg / mm."""
    def fill(p):
        base = np.sin(p[:, 0] / 60.0) * np.cos(p[:, 1] / 50.0) + 0.2 * np.sin(p[:, 2] / 100.0)
        return scale * np.stack([0.25 * base, -0.2 * base, 0.1 * base + 0.05], axis=1)
    return CompTable(machine="test_corr", version=version, axes=CORR_AXES, motors=CORR_MOTORS,
                     values=fill(CompTable(machine="x", version=1, axes=CORR_AXES, motors=CORR_MOTORS,
                                           values=np.zeros((6, 5, 3, 3))).nodes().reshape(-1, 3)).reshape(6, 5, 3, 3),
                     reference="controller").validate()


def _corr_header_cases():
    h = Header.of(corrections())
    assert h.reference == plc_types.REFERENCE_CONTROLLER and h.reference_crc == 0
    cases = []
    for field in ("motor_min", "motor_max", "max_step"):
        for k in (0, 2):
            for name, v in {**HOSTILE, "beyond CORRECTION_ABS_MAX": math.copysign(
                    CORRECTION_ABS_MAX * (1 + 1e-12), -1.0 if field == "motor_min" else 1.0)}.items():
                if name in ("denormal", "-zero") and field != "max_step":
                    continue
                if name == "beyond CORRECTION_ABS_MAX" and field == "max_step":
                    continue                          # the step bound is not capped (it is below 2 x the bounds)
                status = Status.STEP_TOO_LARGE if name == "denormal" else Status.LIMITS    # a valid, tiny bound
                cases.append(pytest.param(replace(h, **{field: _set(getattr(h, field), k, v)}), status,
                                          id=f"corr:{field}[{k}]={name}"))
    cases += [pytest.param(replace(h, reference_crc=1), Status.REFERENCE_MISMATCH, id="corr:reference crc 1"),
              pytest.param(replace(h, reference_crc=0xFFFFFFFF), Status.REFERENCE_MISMATCH, id="corr:reference crc -1"),
              pytest.param(replace(h, reference=3), Status.REFERENCE_MISMATCH, id="corr:reference=3"),
              pytest.param(replace(h, motor_min=h.motor_max, motor_max=h.motor_min), Status.LIMITS,
                           id="corr:bounds reversed"),
              pytest.param(replace(h, n_motors=7), Status.GRID_SIZE, id="corr:nMotors=7"),
              pytest.param(replace(h, n=(6, 5, 65535)), Status.GRID_SIZE, id="corr:third axis overflowing")]
    return cases


@pytest.mark.parametrize("header, status", _corr_header_cases())
def test_hostile_correction_header_is_refused_and_the_task_runs_on(header, status):
    """Whatever a header of a correction table says, the task runs on and refuses it with the code that
    names the field (the CRC matches the header, so the header itself is judged)."""
    table = corrections()
    plc = _plc(table)
    st = _commit(plc, _with_crc(header, table.values), table=table)
    _assert_survived_and_refused(plc, st)
    assert st.status == status, st


def _corr_value_cases():
    cases = [pytest.param(v, Status.NOT_FINITE, "not_finite", id=f"corr:{k}") for k, v in HOSTILE.items()
             if k in ("nan", "+inf", "-inf")]
    cases += [pytest.param(v, Status.OUT_OF_RANGE, "out_of_range", id=f"corr:{k}") for k, v in HOSTILE.items()
              if k in ("huge", "-huge")]
    cases += [pytest.param(0.5 + 1e-9, Status.OUT_OF_RANGE, "out_of_range", id="corr:just above the bound"),
              pytest.param(-0.5 - 1e-9, Status.OUT_OF_RANGE, "out_of_range", id="corr:just below the bound"),
              pytest.param("step", Status.STEP_TOO_LARGE, "step", id="corr:step to a neighbour above max_step")]
    return cases


@pytest.mark.parametrize("value, status, kind", _corr_value_cases())
def test_hostile_correction_value_is_refused_as_python_refuses_it(value, status, kind):
    """A correction that is not finite, outside its motor's correction bounds, or steps too far: the PLC
    refuses it (the task runs on) with the verdict CompTable.defect gives the same table."""
    table = corrections()
    values = table.values.copy()
    if value == "step":
        values[2, 3, 1, 2] = values[2, 3, 2, 2] + (0.21 if values[2, 3, 2, 2] < 0.25 else -0.21)
    else:
        values[2, 3, 1, 2] = value
    d = replace(table, values=values).defect()
    assert d is not None and (d.kind, d.field, d.node) == (kind, "dm3_mm", (2, 3, 1) if value != "step" else d.node)
    plc = _plc(table)
    st = _commit(plc, _with_crc(Header.of(table), values), values=values, table=table)
    _assert_survived_and_refused(plc, st)
    assert st.status == status, st


def test_correction_bounds_are_the_plcs_cap_at_most():
    """Bounds of exactly +-CORRECTION_ABS_MAX are accepted (and the Python constant is the PLC's)."""
    rt = PlcTwin().runtime
    assert rt.constant("GVL_CompTableParam.CORRECTION_ABS_MAX") == CORRECTION_ABS_MAX
    table = corrections()
    wide = [Motor(m.name, m.unit, -CORRECTION_ABS_MAX, CORRECTION_ABS_MAX, m.max_step) for m in table.motors]
    table = CompTable(machine=table.machine, version=2, axes=table.axes, motors=wide, values=table.values,
                      reference="controller").validate()
    plc = _plc(table)
    st = _commit(plc, Header.of(table), table=table)
    assert not plc.stopped and (st.status, st.active_version) == (Status.OK, 2)
    too_wide = replace(table, motors=tuple(replace(m, max=CORRECTION_ABS_MAX * (1 + 1e-12)) for m in wide))
    assert too_wide.defect().kind == "limits"


def test_checking_a_full_correction_table_stays_within_the_cycle_budget():
    """A 20 000-value correction table is checked phase by phase within BUDGET_BYTES_PER_CYCLE: its
    busiest cycle does no more work than the same grid of absolute commands (the correction bounds add
    no per-value work), no nominal IK is computed, and it takes as many cycles."""
    axes = [Axis("x", "mm", -50.0, 70.0, 40), Axis("y", "mm", -30.0, 40.0, 25), Axis("z", "mm", -900.0, -700.0, 10)]
    motors = [Motor(f"m{k + 1}", "deg", -0.5, 0.5, 0.2) for k in range(2)]
    x = CompTable(machine="t", version=2, axes=axes, motors=motors, values=np.zeros((40, 25, 10, 2))).nodes()
    values = 0.3 * np.sin(x[..., :2] / np.array([60.0, 50.0]))
    work = {}
    for reference in ("controller", None):
        table = CompTable(machine="t", version=2, axes=axes, motors=motors, values=values,
                          reference=reference).validate()
        assert table.values.size == plc_types.NVALUES_MAX
        plc = _plc(table)
        rt = plc.runtime
        rt.reset_work_max()
        start = plc.cycle_count
        st = _commit(plc, Header.of(table), table=table)
        assert not plc.stopped and (st.status, st.active_version) == (Status.OK, 2)
        work[reference] = (dict(rt.work_max), rt.calls_max.get("F_CompTableNominalIk", 0), plc.cycle_count - start)
    (corr, ik_corr, n_corr), (absolute, _, n_abs) = work["controller"], work[None]
    assert ik_corr == 0 and n_corr == n_abs, work
    assert corr["statements"] <= absolute["statements"] + 16, work
    assert corr["bytes_copied"] <= rt.constant("GVL_CompTableParam.BUDGET_BYTES_PER_CYCLE") + INTERFACE_COPIES, work
