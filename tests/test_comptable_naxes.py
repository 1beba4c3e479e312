"""Format-4 tables over 1, 2 and 3 task axes with 1 and 3 motors: file -> push -> PLC (real pyads against the
ADS mock, real pymodbus against the Modbus mock), and the PLC's own lookup (the ST of FB_CompTableLookup,
interpreted) at off-node points against scipy's RegularGridInterpolator, a multilinear interpolant written
independently of pmcal. Tables of absolute commands and of corrections to the controller's own IK
(nReference = 2: the PLC answers the interpolated correction, flagged bCorrection). Hostile 3-axis tables
and targets never stop the task."""

from __future__ import annotations

import zlib
from dataclasses import replace

import numpy as np
import pytest
from scipy.interpolate import RegularGridInterpolator

from pmcal.bridge.comptable import NVALUES_MAX, Axis, CompTable, Motor
from pmcal.bridge.simulator.plc_runtime import PlcTwin
from pmcal.bridge.plc_types import LOOKUP_WRITES, Header, LookupIn, LookupOut, LookupResult, Status
from pmcal.bridge.transfer import PushOptions, push
from pmcal.errors import InputError
from tests.bridge_fixtures import ads_link, ads_plc, modbus_link, modbus_plc  # noqa: F401
from tests.test_plc_hostile import HOSTILE, _commit

GRIDS = {1: [Axis("x", "mm", -50.0, 70.0, 7)],
         2: [Axis("x", "mm", -50.0, 70.0, 6), Axis("rz", "deg", -10.0, 25.0, 5)],
         3: [Axis("x", "mm", -50.0, 70.0, 5), Axis("y", "mm", -30.0, 40.0, 4), Axis("z", "mm", -900.0, -700.0, 3)]}
#: three motors: two revolute (deg), one prismatic (mm)
MOTORS = {1: [Motor("m1", "deg", -90.0, 90.0, 40.0)],
          3: [Motor("m1", "deg", -90.0, 90.0, 40.0), Motor("m2", "deg", -90.0, 90.0, 40.0),
              Motor("m3", "mm", 100.0, 400.0, 150.0)]}


def smooth(points: np.ndarray, n_motors: int) -> np.ndarray:
    """Motor commands (P, N) at task points (P, A): smooth, within MOTORS' limits and steps."""
    x = points / np.array([100.0, 50.0, 1000.0])[:points.shape[1]]
    base = np.sin(1.3 * x).sum(axis=1) + 0.4 * np.cos(x.prod(axis=1))
    out = np.stack([30.0 * base + 5.0 * k for k in range(n_motors)], axis=1)
    if n_motors == 3:
        out[:, 2] = 250.0 + 40.0 * base
    return out


#: correction bounds (deg, deg, mm) of the tables with the controller reference
CORRECTION_MOTORS = {1: [Motor("m1", "deg", -1.0, 1.0, 0.5)],
                     3: [Motor("m1", "deg", -1.0, 1.0, 0.5), Motor("m2", "deg", -1.0, 1.0, 0.5),
                         Motor("m3", "mm", -2.0, 2.0, 1.0)]}


def make(n_axes: int, n_motors: int, version: int = 2, reference: str | None = None) -> CompTable:
    """Absolute commands (``smooth``), or with ``reference="controller"`` the corrections from a nominal IK
    ``smooth`` to a calibrated one ``smooth + 0.3 * smooth(0.8 x) / 30`` (at most ~0.5 deg, ~1 mm)."""
    if reference is None:
        return CompTable.from_grid(lambda p: smooth(p, n_motors), machine="test_naxes", version=version,
                                   axes=GRIDS[n_axes], motors=MOTORS[n_motors]).validate()
    return CompTable.from_grid(lambda p: smooth(p, n_motors) + 0.01 * smooth(0.8 * p, n_motors) / (
        1.0 + 9.0 * (np.arange(n_motors) == 2)), machine="test_naxes", version=version, axes=GRIDS[n_axes],
                               motors=CORRECTION_MOTORS[n_motors], reference=reference,
                               nominal=lambda p: smooth(p, n_motors)).validate()


def reference_lookup(table: CompTable, points: np.ndarray) -> np.ndarray:
    """scipy's multilinear interpolant of the table's nodes (independent of pmcal's arithmetic)."""
    f = RegularGridInterpolator([a.nodes() for a in table.axes], table.values, method="linear")
    return f(points)


def off_node_points(table: CompTable, count: int = 25, seed: int = 5) -> np.ndarray:
    rng = np.random.default_rng(seed)
    lo = np.array([a.min for a in table.axes])
    hi = np.array([a.max for a in table.axes])
    pts = lo + rng.random((count, table.n_axes)) * (hi - lo)
    pts[0] = hi                                     # the far corner: the last cell, fraction 1
    return pts


CASES = [pytest.param(a, n, None, id=f"{a}axes-{n}motors") for a in (1, 2, 3) for n in (1, 3)] + [
    pytest.param(a, n, "controller", id=f"{a}axes-{n}motors-corrections") for a, n in ((1, 1), (3, 3))]


@pytest.mark.parametrize("n_axes, n_motors, reference", CASES)
@pytest.mark.parametrize("transport", ["ads", "modbus"])
def test_file_push_lookup_matches_scipy(n_axes, n_motors, reference, transport, tmp_path, request):
    table = make(n_axes, n_motors, reference=reference)
    jp, cp = table.save(tmp_path / "t.json")
    back = CompTable.load(jp if transport == "ads" else cp)
    assert back.values.tobytes() == table.values.tobytes() and back.crc32() == table.crc32()
    assert back.columns()[:n_axes] == tuple(a.column for a in table.axes)
    assert back.reference == table.reference and back.reference_code == (2 if reference else 0)
    if reference:
        assert back.columns()[n_axes:] == tuple("d" + m.column for m in table.motors)
        assert np.abs(table.values).max() > 0.05        # a correction field, not zeros
    plc = request.getfixturevalue(f"{transport}_plc")
    plc.twin.configure_for(table)                        # the PLC's MACHINE, NMOTORS, CORRECTIONS
    assert plc.twin.wait_started()
    rep = push((ads_link if transport == "ads" else modbus_link)(plc), back, PushOptions(attempts=1, ack_timeout_s=10.0))
    assert (rep.result, rep.active_version) == ("ok", 2)
    header, values = plc.twin.active_table()
    assert (header.n_axes, header.n_motors, header.n, header.reference, header.reference_crc, values.tobytes()) == (
        n_axes, n_motors, table.shape, 2 if reference else 0, 0, table.values.tobytes())
    assert header.prismatic == (4 if n_motors == 3 else 0)
    pts = off_node_points(table)
    want = reference_lookup(table, pts)
    got = []
    make_link = ads_link if transport == "ads" else modbus_link
    with make_link(plc, writes=LOOKUP_WRITES) as link:
        for p, w in zip(pts, want):
            out = link.lookup(*p)
            assert (out.result, out.n_motors, out.table_version, out.correction) == (
                LookupResult.OK, n_motors, 2, reference is not None)
            np.testing.assert_allclose(out.m, w, rtol=0, atol=1e-9)
            got.append(out.m)
        outside = pts[1].copy()
        outside[-1] = table.axes[-1].max + 1e-6
        assert link.lookup(*outside).result == LookupResult.OUT_OF_GRID
    # the Python copy of the PLC arithmetic (CompTable.lookup) is bit-identical to the PLC's answers
    assert np.array(got).tobytes() == table.lookup(pts).tobytes()


def test_python_lookup_is_the_plc_arithmetic_and_scipy_multilinear():
    for n_axes in (1, 2, 3):
        table = make(n_axes, 3)
        pts = off_node_points(table, 200)
        np.testing.assert_allclose(table.lookup(pts), reference_lookup(table, pts), rtol=0, atol=1e-9)
        nodes = table.nodes().reshape(-1, n_axes)
        np.testing.assert_allclose(table.lookup(nodes), table.values.reshape(-1, 3), rtol=0, atol=1e-12)


@pytest.mark.parametrize("what, status", [("range", Status.OUT_OF_RANGE), ("step", Status.STEP_TOO_LARGE),
                                          ("nan", Status.NOT_FINITE)])
def test_python_validation_mirrors_the_plc_per_motor(what, status):
    """The defect found locally is the PLC's verdict on the same table: motor m3 (mm) along axis z."""
    table = make(3, 3, version=2)
    values = table.values.copy()
    if what == "range":
        values[2, 1, 1, 2] = 401.0                            # above m3's 400 mm (m1/m2 allow up to 90)
    elif what == "step":
        values[2, 1, 1, 2] = values[2, 1, 2, 2] + 151.0 if values[2, 1, 2, 2] < 249.0 else values[2, 1, 2, 2] - 151.0
        values[2, 1, 1, 2] = min(max(values[2, 1, 1, 2], 100.0), 400.0)
    else:
        values[2, 1, 1, 2] = np.nan
    bad = replace(table, values=values)
    d = bad.defect()
    kind = {"range": "out_of_range", "step": "step", "nan": "not_finite"}[what]
    assert d is not None and (d.kind, d.field) == (kind, "m3_mm")
    with pytest.raises(InputError, match="m3"):
        bad.validate()
    plc = _plc_for(make(3, 3, version=1))
    plc.seed(make(3, 3, version=1))
    header = replace(Header.of(bad), crc=zlib.crc32(values.tobytes(), zlib.crc32(replace(Header.of(bad), crc=0).pack())))
    st = _commit(plc, header, values=values, table=bad)
    assert not plc.stopped and st.status == status and st.active_version == 1


def _plc_for(table) -> PlcTwin:
    """A PLC configured for ``table``'s machine, motors and kind (GVL_CompTableParam)."""
    plc = PlcTwin()
    plc.configure_for(table)
    return plc


def test_grid_sizes_beyond_the_plc_are_refused_locally():
    big = [Axis("x", "mm", 0, 1, 100), Axis("y", "mm", 0, 1, 100)]
    ok = CompTable(machine="m", version=1, axes=big, motors=MOTORS[1] * 2, values=np.zeros((100, 100, 2)))
    assert ok.size_defect() is None and ok.values.size == NVALUES_MAX
    too_many = CompTable(machine="m", version=1, axes=big, motors=MOTORS[3], values=np.zeros((100, 100, 3)))
    assert too_many.defect().kind == "grid_size"
    seven = CompTable(machine="m", version=1, axes=GRIDS[1], motors=MOTORS[1] * 7, values=np.zeros((7, 7)))
    assert "motors" in seven.defect().message
    four = [Axis(f"a{k}", "mm", 0, 1, 2) for k in range(4)]
    assert CompTable(machine="m", version=1, axes=four, motors=MOTORS[1],
                     values=np.zeros((2, 2, 2, 2, 1))).defect().kind == "grid_size"


@pytest.mark.parametrize("value", [pytest.param(v, id=k) for k, v in HOSTILE.items() if k not in ("denormal", "-zero")])
def test_hostile_value_in_a_3_axis_table_never_stops_the_task(value):
    table = make(3, 3)
    values = table.values.copy()
    values[4, 3, 2, 1] = value                                # the very last node
    header = replace(Header.of(table), crc=zlib.crc32(values.tobytes(),
                                                      zlib.crc32(replace(Header.of(table), crc=0).pack())))
    plc = _plc_for(make(3, 3, version=1))
    plc.seed(make(3, 3, version=1))
    st = _commit(plc, header, values=values, table=table)
    assert not plc.stopped, plc.fault
    assert st.status.is_rejection and st.active_version == 1


@pytest.mark.parametrize("reference", [None, "controller"])
def test_hostile_3_axis_targets_never_stop_the_task(reference):
    """Inside the grid the interpolation (for a correction table the correction, flagged bCorrection); a
    NaN, infinite or outside coordinate gives OUT_OF_GRID, every aM 0 and no flag."""
    table = make(3, 3, reference=reference)
    plc = _plc_for(table)
    plc.seed(table)
    seq = 0
    inside = [0.0, 0.0, -800.0]
    for k in range(3):
        for name, v in HOSTILE.items():
            x = list(inside)
            x[k] = v
            seq += 1
            plc.write_symbol("lookup_in", LookupIn(tuple(x), seq).pack())
            assert plc.cycle(), plc.fault
            out = LookupOut.unpack(plc.read_symbol("lookup_out"))
            a = table.axes[k]
            want = LookupResult.OK if a.min <= v <= a.max else LookupResult.OUT_OF_GRID
            assert (out.seq, out.result) == (seq, want), (k, name)
            assert out.correction == (want == LookupResult.OK and reference is not None)
            if want == LookupResult.OK:
                np.testing.assert_allclose(out.m, reference_lookup(table, np.array([x]))[0], rtol=0, atol=1e-9)
            else:
                assert out.n_motors == 0 and plc.read_symbol("lookup_out")[:48] == bytes(48)   # aM all 0


def test_a_correction_table_is_its_own_kind_in_python():
    """nReference 2 in the header (nReferenceCrc 0), sealed by the CRC (the same values as absolute
    commands give another CRC); the lookup is the plain interpolation; the commands are not the table's to
    know; a defect names the correction column."""
    corr = make(3, 3, reference="controller")
    same = CompTable(machine=corr.machine, version=corr.version, axes=corr.axes, motors=corr.motors,
                     values=corr.values)
    assert Header.of(corr).reference == 2 and Header.of(corr).reference_crc == 0 and Header.of(same).reference == 0
    assert corr.crc32() != same.crc32()
    pts = off_node_points(corr, 50)
    assert corr.lookup(pts).tobytes() == same.lookup(pts).tobytes()
    with pytest.raises(ValueError, match="controller"):
        corr.commands_at_nodes()
    with pytest.raises(ValueError, match="nominal="):
        CompTable.from_grid(lambda p: smooth(p, 3), machine="m", version=1, axes=GRIDS[3], motors=MOTORS[3],
                            reference="controller")
    values = corr.values.copy()
    values[1, 2, 0, 2] = 2.5                                   # beyond m3's correction bound of 2 mm
    d = replace(corr, values=values).defect()
    assert (d.kind, d.field, d.node) == ("out_of_range", "dm3_mm", (1, 2, 0)) and "correction bounds" in d.message
