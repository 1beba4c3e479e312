"""The compensation table: CRC variant, validation, JSON/CSV files, interpolation (calib.comptable)."""

from __future__ import annotations

import json

from dataclasses import replace

import numpy as np
import pytest
from scipy.interpolate import RegularGridInterpolator

from pmcal.bridge.comptable import CompTable, bilinear, crc32
from pmcal.errors import InputError
from tests.bridge_fixtures import MAX_STEP_DEG, make_table, nominal_setpoints


LIMITS = dict(phi_min_deg=0, phi_max_deg=360, theta_min_deg=0, theta_max_deg=60, m_min_deg=-180, m_max_deg=180,
              max_step_deg=10)


def crc32_bitwise(data: bytes, crc: int = 0) -> int:
    """Independent CRC-32 (IEEE 802.3): reflected polynomial 0xEDB88320, bit by bit, init/final XOR."""
    reg = crc ^ 0xFFFFFFFF
    for byte in data:
        reg ^= byte
        for _ in range(8):
            reg = (reg >> 1) ^ 0xEDB88320 if reg & 1 else reg >> 1
    return reg ^ 0xFFFFFFFF


def header_image(table, crc: int) -> bytes:
    """ST_CompTableHeader of format 4 as the DUT comments lay it out (offsets 0..247), field by field."""
    import struct

    ref = table.reference
    pad = lambda xs, n: list(xs) + [0] * (n - len(xs))                           # noqa: E731
    out = struct.pack("<3d", *pad([a.min for a in table.axes], 3))                 # 0 aAxisMin
    out += struct.pack("<3d", *pad([a.max for a in table.axes], 3))                # 24 aAxisMax
    out += struct.pack("<6d", *pad([m.min for m in table.motors], 6))              # 48 aMotorMin
    out += struct.pack("<6d", *pad([m.max for m in table.motors], 6))              # 96 aMotorMax
    out += struct.pack("<6d", *pad([m.max_step for m in table.motors], 6))         # 144 aMaxStep
    out += struct.pack("<I", table.version)                                        # 192 nTableVersion
    out += struct.pack("<2H", 4, len(table.axes))                                  # 196 nFormatVersion, nAxes
    out += struct.pack("<3H", *pad([a.n for a in table.axes], 3))                  # 200 aN
    out += struct.pack("<2H", len(table.motors), 0 if ref is None else 1)          # 206 nMotors, nReference
    out += struct.pack("<H", sum(1 << k for k, m in enumerate(table.motors) if m.unit == "mm"))  # 210
    out += struct.pack("<I", crc)                                                  # 212 nCrc
    out += struct.pack("<I", 0 if ref is None else crc32_bitwise(ref.pack()))      # 216 nReferenceCrc
    out += table.machine.encode().ljust(28, b"\0")                                # 220 sMachine STRING(27)
    return out


def limits_of(table) -> dict:
    """The format-3 keywords of a 2-axis, 2-motor table."""
    return dict(phi_min_deg=table.phi_min_deg, phi_max_deg=table.phi_max_deg, theta_min_deg=table.theta_min_deg,
                theta_max_deg=table.theta_max_deg, m_min_deg=table.m_min_deg, m_max_deg=table.m_max_deg,
                max_step_deg=table.max_step_deg)


# ---- CRC ----------------------------------------------------------------------------------

def test_crc_pinned_vector_is_ieee_crc32():
    # the check value of CRC-32/ISO-HDLC (zlib.crc32); FB_CompTableCheck refuses every table if its
    # F_CompTableCrc32 gives anything else
    assert crc32(b"123456789") == crc32_bitwise(b"123456789") == 0xCBF43926
    assert crc32(b"") == 0


def test_crc_covers_the_header_with_its_crc_zeroed_then_the_rows():
    table = make_table(n_phi=9, n_theta=5)
    assert table.header_bytes(0) == header_image(table, 0) and len(header_image(table, 0)) == 248
    crc = crc32(header_image(table, 0))
    for i in range(table.n_phi):          # FB_CompTableCheck: chained over the values, split over cycles
        crc = crc32(table.values[i].tobytes(), crc)
    assert crc == table.crc32() == crc32_bitwise(header_image(table, 0) + table.data_bytes())
    # the header counts: another version or machine gives another CRC over the same data
    assert table.with_version(table.version + 1).crc32() != table.crc32()


def test_crc_covers_the_little_endian_lreal_layout():
    values = np.zeros((2, 2, 2))
    values[0, 0, 0] = 1.0
    table = CompTable(machine="m", version=1, values=values, **LIMITS)
    expected = bytes.fromhex("000000000000f03f") + bytes(7 * 8)      # LREAL 1.0, then seven zeros
    assert table.data_bytes() == expected
    assert table.crc32() == crc32_bitwise(header_image(table, 0) + expected)


# ---- validation ---------------------------------------------------------------------------

def test_valid_nominal_table_passes_and_covers_the_workspace():
    table = make_table(version=3, n_phi=37, n_theta=13).validate(active_version=2)
    assert table.values.shape == (37, 13, 2)
    # home pose (theta = 0): both motors at the nominal home angle -39.351 deg (docs/ocpm_2dof.md)
    np.testing.assert_allclose(table.commands_at_nodes()[:, 0, :], -39.351, atol=5e-4)


@pytest.mark.parametrize("what, field, kind", [
    ("nan", "m1_deg", "not a finite number"),
    ("inf", "m2_deg", "not a finite number"),
    ("range", "m1_deg", "outside the motor limits"),
    ("step", "m2_deg", "exceeds max_step"),
])
def test_bad_values_are_refused_naming_row_and_field(what, field, kind):
    table = make_table(n_phi=37, n_theta=13)          # nominal steps up to 9.8 deg < MAX_STEP_DEG
    i, j = 4, 2
    k = 0 if field == "m1_deg" else 1
    # range and step apply to the absolute command: nominal (reference) + stored correction
    table.values[i, j, k] = {"nan": np.nan, "inf": np.inf, "range": 75.0 - table.nominal_at_nodes()[i, j, k],
                             "step": table.values[i, j, k] + MAX_STEP_DEG + 1.0}[what]
    with pytest.raises(InputError) as exc:
        table.validate()
    if what == "step":      # the first offending pair is the spike's neighbour before it along phi
        i -= 1
    assert exc.value.row == i * table.n_theta + j + 1
    assert exc.value.field == field
    assert kind in str(exc.value)


@pytest.mark.parametrize("n_phi, n_theta", [(1, 10), (10, 1), (101, 100), (100, 101)])
def test_wrong_grid_size_is_refused(n_phi, n_theta):
    table = CompTable(machine="m", version=1, values=np.zeros((n_phi, n_theta, 2)), **LIMITS)
    assert table.defect().kind == "grid_size"
    with pytest.raises(InputError, match="grid"):
        table.validate()


def test_stale_and_equal_versions_are_refused():
    table = make_table(version=7)
    table.validate(active_version=6)
    for active in (7, 8):
        with pytest.raises(InputError, match="not newer"):
            table.validate(active_version=active)
    with pytest.raises(InputError, match="outside 1"):
        make_table(version=0).validate()


def test_limits_and_grid_limits_are_checked():
    t = make_table()
    phi, theta = t.axes
    assert replace(t, axes=(replace(phi, max=phi.min), theta)).defect().kind == "grid_limits"
    assert replace(t, axes=(replace(phi, max=400.0), theta)).defect().kind == "grid_limits"
    m1, m2 = t.motors
    assert replace(t, motors=(m1, replace(m2, min=10.0, max=-10.0))).defect().kind == "limits"
    assert replace(t, motors=(replace(m1, max_step=float("nan")), m2)).defect().kind == "limits"


# ---- files ----------------------------------------------------------------------------------

def test_json_and_csv_round_trip_bit_exact(tmp_path):
    table = make_table(version=5, n_phi=100, n_theta=100)
    table.values[3, 4, 1] = -0.0                    # signs of zero survive too
    jp, cp = table.save(tmp_path / "comp.json")
    for back in (CompTable.load(jp), CompTable.load(cp)):
        assert back.values.tobytes() == table.values.tobytes()
        assert back.crc32() == table.crc32() and back.sha256() == table.sha256()
        assert (back.version, back.machine, back.n_phi, back.n_theta) == (5, "ocpm_2dof", 100, 100)
    doc = json.loads(jp.read_text())
    assert doc["format"] == "pmcal-comptable" and doc["format_version"] == 4
    assert doc["crc32"] == f"0x{table.crc32():08X}" and doc["sha256"] == table.sha256()
    lines = cp.read_text().splitlines()
    assert lines[0].startswith("# pmcal-comptable") and "phi_deg,theta_deg,dm1_deg,dm2_deg" in lines


def test_edited_file_fails_its_checksum(tmp_path):
    jp, cp = make_table().save(tmp_path / "comp.json")
    doc = json.loads(jp.read_text())
    doc["values"][2][3][0] += 1e-9
    jp.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="CRC mismatch") as exc:
        CompTable.load(jp)
    assert exc.value.file == str(jp) and exc.value.field == "crc32"


def test_csv_errors_name_file_row_and_field(tmp_path):
    _, cp = make_table(n_phi=4, n_theta=3).save(tmp_path / "comp.json")
    lines = cp.read_text().splitlines()
    first = next(i for i, l in enumerate(lines) if l.startswith("phi_deg")) + 1
    bad = lines.copy()
    bad[first + 4] = bad[first + 4].rsplit(",", 1)[0] + ",abc"       # data row 5, m2
    cp.write_text("\n".join(bad) + "\n")
    with pytest.raises(InputError) as exc:
        CompTable.load(cp)
    assert (exc.value.file, exc.value.row, exc.value.field) == (str(cp), 5, "dm2_deg")
    bad = lines.copy()
    bad[first + 1] = "5," + bad[first + 1].split(",", 1)[1]           # row 2: phi is not the node
    cp.write_text("\n".join(bad) + "\n")
    with pytest.raises(InputError) as exc:
        CompTable.load(cp)
    assert (exc.value.row, exc.value.field) == (2, "phi_deg")


def test_nan_in_csv_reads_and_is_refused_by_validate(tmp_path):
    table = make_table(n_phi=4, n_theta=3)
    table.values[1, 2, 0] = np.nan
    cp = tmp_path / "comp.csv"
    table.to_csv(cp)
    back = CompTable.load(cp)
    with pytest.raises(InputError) as exc:
        back.validate()
    assert (exc.value.file, exc.value.row, exc.value.field) == (str(cp), 1 * 3 + 2 + 1, "m1_deg")


def test_invalid_table_is_not_written_as_json(tmp_path):
    table = make_table()
    table.values[0, 0, 0] = np.nan
    with pytest.raises(InputError):
        table.to_json(tmp_path / "comp.json")
    assert list(tmp_path.iterdir()) == []


def test_missing_and_foreign_files(tmp_path):
    with pytest.raises(InputError, match="not found"):
        CompTable.load(tmp_path / "nope.json")
    p = tmp_path / "other.json"
    p.write_text('{"format": "something-else"}')
    with pytest.raises(InputError, match="not a compensation table"):
        CompTable.load(p)


# ---- interpolation ------------------------------------------------------------------------

def test_interpolation_hits_the_nodes_and_matches_scipy_between():
    table = make_table(n_phi=37, n_theta=13, reference=None)     # absolute commands: bilinear alone
    pp, tt = np.meshgrid(table.phi_nodes_deg(), table.theta_nodes_deg(), indexing="ij")
    # a + (b - a) * t is exact at t = 0 and within an ulp-sized rounding at t = 1
    np.testing.assert_allclose(table.interpolate(pp, tt), table.values, rtol=0, atol=1e-12)
    rng = np.random.default_rng(0)
    phi, theta = rng.uniform(0, 360, 500), rng.uniform(0, 60, 500)
    ref = RegularGridInterpolator((table.phi_nodes_deg(), table.theta_nodes_deg()), table.values)(
        np.c_[phi, theta])
    np.testing.assert_allclose(table.interpolate(phi, theta), ref, rtol=0, atol=1e-12)


def test_fine_table_reproduces_the_inverse_kinematics_within_the_bilinear_bound():
    table = make_table(n_phi=100, n_theta=100, reference=None)
    rng = np.random.default_rng(1)
    phi, theta = rng.uniform(0, 360, 300), rng.uniform(0, 60, 300)
    err = np.abs(table.interpolate(phi, theta) - nominal_setpoints(phi, theta))
    # bilinear error <= (h^2 |f_phiphi| + k^2 |f_thetatheta|) / 8; h^2 f'' is the table's 2nd difference
    bound = (np.abs(np.diff(table.values, 2, axis=0)).max() + np.abs(np.diff(table.values, 2, axis=1)).max()) / 8
    assert 0.005 < err.max() <= 1.2 * bound < 0.05        # deg


def test_interpolation_refuses_targets_outside_the_grid():
    table = make_table()
    with pytest.raises(InputError, match="outside the table grid"):
        table.interpolate([10.0, 370.0], [5.0, 5.0])
    m, inside = bilinear(table.values, (0, 360), (0, 60), [10.0, np.nan, 10.0], [5.0, 5.0, 61.0])
    assert inside.tolist() == [True, False, False] and np.isnan(m[1:]).all()


# ---- format 2: reference, version-1 files, required checksums ---------------------------------

def _v1_file(tmp_path, table):
    """A format-1 JSON file as the version-1 writer produced it (absolute values, SHA over values)."""
    import binascii
    import hashlib

    doc = {"format": "pmcal-comptable", "format_version": 1, "machine": table.machine,
           "table_version": int(table.version),
           "grid": {"n_phi": table.n_phi, "n_theta": table.n_theta, "phi_min_deg": table.phi_min_deg,
                    "phi_max_deg": table.phi_max_deg, "theta_min_deg": table.theta_min_deg,
                    "theta_max_deg": table.theta_max_deg},
           "limits": {"m_min_deg": table.m_min_deg, "m_max_deg": table.m_max_deg, "max_step_deg": table.max_step_deg}}
                                      # formats 1 and 2: CRC-16/CCITT-FALSE over the values
    doc["crc16_ccitt"] = f"0x{binascii.crc_hqx(table.values.tobytes(), 0xFFFF):04X}"
    doc["sha256"] = hashlib.sha256(table.values.tobytes()).hexdigest()
    doc["values"] = table.values.tolist()
    p = tmp_path / "v1.json"
    p.write_text(json.dumps(doc))
    return p


def test_version_1_file_is_read_as_absolute_commands_with_the_same_lookup(tmp_path):
    ref_table = make_table(version=4, n_phi=37, n_theta=13)
    absolute = CompTable(machine="ocpm_2dof", version=4, values=ref_table.commands_at_nodes(),
                         **limits_of(ref_table))
    back = CompTable.load(_v1_file(tmp_path, absolute))
    assert back.reference is None and back.values.tobytes() == absolute.values.tobytes()
    back.validate()
    # saving writes format 4 (reference kind none), which reads back to the same table
    jp, cp = back.save(tmp_path / "v2.json")
    assert json.loads(jp.read_text())["reference"] == {"kind": "none"}
    for again in (CompTable.load(jp), CompTable.load(cp)):
        assert again.reference is None and again.values.tobytes() == absolute.values.tobytes()


@pytest.mark.parametrize("version", [0, 5, "2"])
def test_unknown_format_version_is_refused(tmp_path, version):
    jp, _ = make_table().save(tmp_path / "comp.json")
    doc = json.loads(jp.read_text())
    doc["format_version"] = version
    jp.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="format_version") as exc:
        CompTable.load(jp)
    assert exc.value.field == "format_version"


@pytest.mark.parametrize("drop", ["crc32", "sha256"])
def test_file_without_checksums_is_refused(tmp_path, drop):
    jp, cp = make_table().save(tmp_path / "comp.json")
    doc = json.loads(jp.read_text())
    del doc[drop]
    jp.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=f"no {drop}") as exc:
        CompTable.load(jp)
    assert exc.value.field == drop
    lines = [ln for ln in cp.read_text().splitlines() if not ln.startswith("# crc32")]
    cp.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="no crc32"):
        CompTable.load(cp)


def test_edited_reference_fails_the_checksums(tmp_path):
    jp, _ = make_table().save(tmp_path / "comp.json")
    doc = json.loads(jp.read_text())
    doc["reference"]["l_mm"] += 0.001
    jp.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="CRC mismatch|SHA-256 mismatch"):
        CompTable.load(jp)


def test_nominal_reference_equals_the_mechanism_inverse_kinematics():
    """bridge/nominal.py (the ST arithmetic) against pmcal.mechanism's vectorised real IK, errors zero."""
    from pmcal.bridge.nominal import NominalReference

    rng = np.random.default_rng(3)
    phi, theta = rng.uniform(0, 360, 2000), rng.uniform(0, 60, 2000)
    np.testing.assert_allclose(NominalReference.default().commands_deg(phi, theta), nominal_setpoints(phi, theta),
                               rtol=0, atol=1e-11)
    # the table stores only the calibration's correction: zero for the nominal machine
    assert np.abs(make_table(n_phi=37, n_theta=13).values).max() < 1e-11


def test_the_plcs_reference_geometry_is_the_machines():
    """The nominal-IK reference a table is built on is the shipped PLC's REF_* constants; they must be
    ocpm_2dof's nominal geometry (machine.toml), or every nominal-IK table would be refused (nReferenceCrc)."""
    from pmcal.bridge.nominal import NominalReference
    from pmcal.mechanism.ocpm.config import default_geometry

    g = default_geometry()
    psi = [float(np.rad2deg(g.psi[j - 1])) for j in g.actuated[:2]]
    assert NominalReference.default() == NominalReference(float(g.a), float(g.h), float(g.l), *psi)
