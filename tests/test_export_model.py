"""``pmcal export-model`` (issue 23): the calibrated MJCF reproduces the identified model and simulates.

The exported file is loaded with ``mujoco.MjModel.from_xml_path`` only (nothing of pmcal's model building);
its closed chain is assembled at the campaign's commands from a nominal start and compared with the
identified model's own predictions (ocpm_2dof: :class:`FullChainModel`, the model identify fits; planar:
the closed-form forward kinematics of the perturbed geometry, eq. 5-8 of the paper).
"""

import json
from pathlib import Path
import tomllib

import mujoco
import numpy as np
import pytest

from pmcal.ocpm.calibration import identify
from pmcal.cli import main
from pmcal.mechanism.ocpm.config import default_geometry
from pmcal.mechanism.ocpm.params import PAPER_TABLE2, ErrorSet
from pmcal.mechanism.planar.kinematics import forward, mm_vector
from pmcal.twin.ocpm.assembly import BatchAssembler, Stiffness
from pmcal.twin.ocpm.campaign import plan_campaign, run_campaign
from pmcal.twin.export import simulate
from pmcal.twin.ocpm.forward import FullChainModel
from pmcal.twin.ocpm.machine import Twin
from pmcal.twin.ocpm.model import MM, ModelIndex
from pmcal.mechanism.machine_spec import MachineSpec
from pmcal.mjcf import machine_dir
from pmcal.twin.closed_chain import ClosedChainTwin
from pmcal.twin.tracker import LaserTracker
from pmcal.planar.io import read_measurements as read_planar, read_params as read_planar_params
from pmcal.twin.planar.config import default_machine

TOL_MM = 1e-6


def custom(m, name):
    i = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_NUMERIC, name)
    a = m.numeric_adr[i]
    return m.numeric_data[a:a + m.numeric_size[i]]


def no_warnings(d):
    return all(w.number == 0 for w in d.warning)


@pytest.fixture(scope="module")
def ocpm_case(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ocpm")
    meas = run_campaign(Twin(PAPER_TABLE2), plan_campaign(24, 60, seed=5), LaserTracker(0.01, np.random.default_rng(6)))
    cal = identify(meas)
    cal.save(tmp / "params.json")
    assert main(["export-model", str(tmp / "params.json"), "-o", str(tmp / "calibrated.xml")]) == 0
    return tmp, meas, cal


def test_ocpm_export_reproduces_identified_model(ocpm_case):
    tmp, meas, cal = ocpm_case
    geom = default_geometry()
    fm = FullChainModel(geom)
    fm.set(ErrorSet.from_dict(cal.params, geom.n_limbs, geom.actuated), cal.document["stiffness_ratio"])
    predicted = fm.predict(meas.m_cmd_deg)[0]
    m = mujoco.MjModel.from_xml_path(str(tmp / "calibrated.xml"))
    idx = ModelIndex.of(m, geom.n_limbs, geom.target_names)
    k_p, ratio = custom(m, "pmcal_passive_closure_stiffness")[0], custom(m, "pmcal_stiffness_ratio")[0]
    assert ratio == pytest.approx(cal.document["stiffness_ratio"], rel=1e-15)
    asm = BatchAssembler(m, idx, Stiffness.reference(k_p, ratio, geom.n_limbs, geom.actuated))
    # start: the nominal machine's configuration; the motor joints at the *commands* (ref carries dtheta)
    q0 = Twin(None, geom).initial_qpos(np.deg2rad(meas.m_cmd_deg))
    res = asm.solve(q0)
    assert res.converged.all()
    targets = asm.sites(len(meas), idx.site_targets) / MM
    assert np.abs(targets - predicted).max() < TOL_MM
    # the zero offsets really are in the model: the commands alone give the identified machine
    assert np.abs(np.rad2deg(m.qpos0[idx.qadr_base[:2]]) + [cal.params["L1.dtheta"], cal.params["L2.dtheta"]]).max() < 1e-12


def test_ocpm_export_simulates_and_holds_home(ocpm_case):
    tmp, _, _ = ocpm_case
    m, d = simulate(tmp / "calibrated.xml", steps=500)
    assert no_warnings(d) and np.isfinite(d.qpos).all()
    m0 = mujoco.MjModel.from_xml_path(str(tmp / "calibrated.xml"))
    d0 = mujoco.MjData(m0)
    mujoco.mj_resetDataKeyframe(m0, d0, 0)
    mujoco.mj_forward(m0, d0)
    sites = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, t) for t in ("T1", "T2", "T3")]
    drift_mm = np.abs(d.site_xpos[sites] - d0.site_xpos[sites]).max() / MM
    assert drift_mm < 1.0                  # gravity sag under servos of 2e5 N m/rad: far below a mm
    doc = tomllib.loads((tmp / "calibrated.toml").read_text())
    assert doc["calibration"]["params"]["L1.dbx"] == cal_value(tmp, "L1.dbx")
    assert doc["machine"]["model"] == "calibrated.xml"


def cal_value(tmp, key):
    return json.loads((tmp / "params.json").read_text())["params"][key]


def test_effects_written_where_mjcf_can_hold_them(ocpm_case, tmp_path, capsys):
    tmp, _, _ = ocpm_case
    doc = json.loads((tmp / "params.json").read_text())
    doc["effects"] = {"joint_compliance": {"value": 5.0e4, "unit": "N m/rad", "interval": [4.8e4, 5.2e4]},
                      "backlash": {"value": 0.0125, "unit": "deg"},
                      "thermal_expansion": {"value": 1.9e-5, "unit": "1/K"}}
    (tmp_path / "p.json").write_text(json.dumps(doc))
    assert main(["export-model", str(tmp_path / "p.json"), "-o", str(tmp_path / "c.xml")]) == 0
    err = capsys.readouterr().err
    assert "backlash" in err and "thermal_expansion" in err
    m = mujoco.MjModel.from_xml_path(str(tmp_path / "c.xml"))
    a = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, "motor1")
    assert m.actuator_gainprm[a, 0] == 5.0e4 and m.actuator_biasprm[a, 1] == -5.0e4
    text = (tmp_path / "c.xml").read_text()
    assert "backlash = 0.0125 deg" in text and "thermal_expansion" in text
    toml = tomllib.loads((tmp_path / "c.toml").read_text())
    assert toml["effects"]["backlash"]["value"] == 0.0125
    assert toml["effects"]["thermal_expansion"]["in_mjcf"] == "not representable in MJCF"
    assert no_warnings(simulate(tmp_path / "c.xml", steps=300)[1])


def test_planar_export_reproduces_identified_model(tmp_path):
    run = lambda *a: main(["--machine", "planar_2dof", *a])  # noqa: E731
    assert run("twin", "measure", "--preset", "group3", "--seed", "2", "-o", str(tmp_path / "m.csv")) == 0
    assert run("identify", str(tmp_path / "m.csv"), "-o", str(tmp_path / "p.json")) == 0     # the paper's 4
    assert run("export-model", str(tmp_path / "p.json"), "-o", str(tmp_path / "planar.xml")) == 0
    machine = default_machine()
    errors, _ = read_planar_params(tmp_path / "p.json")
    theta = read_planar(tmp_path / "m.csv", machine.geometry).theta_cmd
    g = machine.geometry.perturbed(errors)
    predicted = forward(g, theta + errors.dtheta)
    length = np.linalg.norm(mm_vector(g, predicted), axis=1)              # |O1 O2|: what the scale measures
    assert abs(errors.drM).max() > 0.1 and abs(errors.dtheta).max() > 1e-3
    m = mujoco.MjModel.from_xml_path(str(tmp_path / "planar.xml"))
    # the exported file assembled as it stands (no errors added), motor joints at the commands (ref = -dtheta)
    twin = ClosedChainTwin(MachineSpec.load(machine_dir("planar_2dof") / "chain"), model=m)
    cmd = np.rad2deg(theta)
    assert np.abs(twin.forward(cmd) - predicted).max() < TOL_MM
    assert np.abs(twin.observe(cmd)[:, 0] - length).max() < TOL_MM
    assert no_warnings(simulate(tmp_path / "planar.xml", steps=500)[1])


def test_export_bad_input(tmp_path, capsys):
    (tmp_path / "p.json").write_text('{"mechanism": "ocpm_2dof", "params": {"L1.dbx": "x"}}')
    assert main(["export-model", str(tmp_path / "p.json"), "-o", str(tmp_path / "c.xml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "p.json" in err[0] and "L1.dbx" in err[0]
    assert not (tmp_path / "c.xml").exists()


def test_a_planar_file_with_model_null_exports_both_files(tmp_path, capsys):
    """read_params accepts "model": null; export-model wrote the XML, then failed on the TOML (exit 1, a
    TypeError "bug") and left the XML without its TOML. Both texts are made before either file is written."""
    (tmp_path / "p.json").write_text('{"mechanism": "planar_2dof", "model": null, "params": {"dtheta1": 0.1}}')
    assert main(["--machine", "planar_2dof", "export-model", str(tmp_path / "p.json"), "-o",
                 str(tmp_path / "c.xml")]) == 0, capsys.readouterr().err
    assert (tmp_path / "c.xml").is_file() and 'model = ""' in (tmp_path / "c.toml").read_text()


def test_export_refuses_the_paper_model(tmp_path, capsys):
    (tmp_path / "p.json").write_text('{"mechanism": "ocpm_2dof", "model": "paper", "params": {"L1.dbx": 0.1}}')
    assert main(["export-model", str(tmp_path / "p.json"), "-o", str(tmp_path / "c.xml")]) == 2
    assert "field 'model'" in capsys.readouterr().err and not (tmp_path / "c.xml").exists()


# ---------------------------------------------------------------- a machine folder's calibrated model
CORPUS = Path(__file__).parent / "corpus"


def _source(name: str) -> Path:
    """The folder of a built-in machine or of a corpus model (tests/corpus)."""
    from pmcal.mjcf import machine_dir

    return CORPUS / name if (CORPUS / name).is_dir() else machine_dir(name)


#: every corpus model pmcal takes (the gripper is refused at load, tests/test_corpus.py)
CORPUS_MODELS = sorted(p.name for p in CORPUS.iterdir() if (p / "machine.toml").is_file() and p.name != "robotiq_2f85")


@pytest.mark.parametrize("name", ["delta_3dof", "hexapod_6dof", *CORPUS_MODELS])
def test_folder_machine_export_is_the_identified_machine(name, tmp_path, capsys):
    """``pmcal --machine DIR export-model`` on a copy of a folder machine (its MJCF places bodies and sites
    in ``<frame>`` elements; the hexapod's motors are prismatic): with random errors on every frame and
    motor zero, the exported MJCF, read by plain MuJoCo at the twin's assembled configuration (motor joints
    at command - zero), closes every loop (equality residuals ~0; an over-constrained loop, a planar one closed
    by a 3-D connect, keeps the gap its out-of-plane errors leave, as the real part's strain does) and puts the
    tracker nests where the twin with those errors puts them (1e-6 mm); and as a folder of its own (the
    exported TOML as machine.toml) its error-free twin is the identified machine at fresh poses. Every corpus
    model MuJoCo loads (issue 34)."""
    import shutil

    from pmcal.chain import random_errors
    from pmcal.machines import Machine

    folder = tmp_path / f"my_{name}"
    shutil.copytree(_source(name), folder)
    mach = Machine.from_folder(folder)
    rng = np.random.default_rng(11)
    truth = random_errors(mach, rng)
    assert any(k.endswith(".dzero") and v != 0 for k, v in truth.items())
    (tmp_path / "p.json").write_text(json.dumps({"mechanism": mach.name, "params": truth}))
    out = tmp_path / "cal" / "calibrated.xml"
    out.parent.mkdir()
    assert main(["--quiet", "--machine", str(folder), "export-model", str(tmp_path / "p.json"), "-o", str(out)]) == 0
    twin = mach.twin
    cmd = twin.sample_commands(12, rng)
    q = twin.solve(cmd, truth)
    nests = twin.targets(cmd, truth) * MM
    m = mujoco.MjModel.from_xml_path(str(out))
    d = mujoco.MjData(m)
    sites = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, s) for s in mach.spec.targets]
    shift = twin.errors.zero_offset * twin.motor_unit
    for qi, ni in zip(q, nests):
        d.qpos[:] = qi
        d.qpos[twin.motor_qadr] -= shift
        mujoco.mj_forward(m, d)
        eq = d.efc_type == mujoco.mjtConstraint.mjCNSTR_EQUALITY
        if not len(twin.redundant_directions):      # an over-constrained loop keeps the gap its errors leave
            assert np.abs(d.efc_pos[eq]).max() < 1e-9                   # m: every loop closed
        assert np.abs(d.site_xpos[sites] - ni).max() < 1e-9             # m: the nests where the twin has them
    (out.parent / "calibrated.toml").rename(out.parent / "machine.toml")
    again = Machine.from_folder(out.parent)
    fresh = twin.sample_commands(12, rng)
    # a ball-ball rod's free spin, which the errors couple to the nests (gepetto_wl16: 0.1 mm/rad), sits where
    # each solve's path leaves it: the same machine up to far less than the tracker noise
    tol = 1e-6 if not twin.n_free else mach.spec.sigma_mm
    assert np.abs(again.twin.targets(fresh, None) - twin.targets(fresh, truth)).max() < tol    # mm
    if twin.n_free:      # an export written before the marker numeric: known by its machine.toml's first words
        out.write_text(out.read_text().replace('name="pmcal_identified_machine"', 'name="unrelated"'))
        assert Machine.from_folder(out.parent).twin.n_free == twin.n_free


def _tetrahedron_stl(path: Path, size_m: float = 0.01) -> None:
    """A binary STL file of a tetrahedron (4 facets), written without pmcal."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], np.float32) * size_m
    faces = [(0, 2, 1), (0, 1, 3), (0, 3, 2), (1, 2, 3)]
    rec = np.zeros(4, dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    for i, f in enumerate(faces):
        rec["v"][i] = v[list(f)]
    path.write_bytes(b"\0" * 80 + np.uint32(4).tobytes() + rec.tobytes())


def test_export_keeps_mesh_files_of_a_cad_model(tmp_path, capsys):
    """A CAD export's meshes (``compiler meshdir``, a mesh geom on the moving platform): the calibrated MJCF
    written into another folder loads in MuJoCo and draws the same mesh files (paths rewritten relative to
    the output); a missing mesh file is one error line naming it, exit 2, and nothing written."""
    import shutil

    folder = tmp_path / "cad"
    shutil.copytree(CORPUS / "reachy_mini", folder)
    (folder / "assets").mkdir()
    _tetrahedron_stl(folder / "assets" / "plate.stl")
    xml = folder / "reachy_mini.xml"
    text = xml.read_text()
    assert 'meshdir="assets"' in text
    text = text.replace("<asset>", '<asset>\n    <mesh name="plate" file="plate.stl"/>', 1)
    text = text.replace('<site name="nest1"', '<geom type="mesh" mesh="plate" contype="0" conaffinity="0" '
                                              'mass="0"/>\n              <site name="nest1"', 1)
    xml.write_text(text)
    (tmp_path / "p.json").write_text(json.dumps({"mechanism": "reachy_mini", "params": {"xl_330.dx": 0.05}}))
    out = tmp_path / "elsewhere" / "calibrated.xml"
    out.parent.mkdir()
    assert main(["--quiet", "--machine", str(folder), "export-model", str(tmp_path / "p.json"), "-o", str(out)]) == 0
    m = mujoco.MjModel.from_xml_path(str(out))
    assert m.nmesh == 1 and m.mesh_vertnum[0] == 4
    assert "meshdir" not in out.read_text() and "../cad/assets/plate.stl" in out.read_text()

    (folder / "assets" / "plate.stl").unlink()
    out2 = tmp_path / "elsewhere" / "again.xml"
    assert main(["--machine", str(folder), "export-model", str(tmp_path / "p.json"), "-o", str(out2)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "plate.stl" in err[0] and "reachy_mini.xml" in err[0]
    assert not out2.exists() and not out2.with_suffix(".toml").exists()
