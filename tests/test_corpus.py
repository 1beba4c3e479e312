"""Machines not written here (tests/corpus/<name>/: public MJCF models with their licences and the
machine.toml a user writes first, docs/ADDING_A_MACHINE.md) load as machine folders, assemble at their
default configuration, and calibrate on their own twin.

Each model: ``pmcal.Machine.from_folder``; the ``home`` configuration closes every loop (1e-9 mm) at the
motors' home commands; a 48-pose campaign with random errors of the toml's sizes and its tracker noise
(``pmcal --machine DIR twin measure`` through the command line), identified by ``identify``:

- chi2/dof within 6 sigma of 1 (its standard deviation is sqrt(2/dof) for a fit to noise);
- at 12 held-out poses the identified machine predicts the true machine's nests to within 4 tracker sigmas
  RMS (a fit to noise predicts them to about sqrt(rank / observations) sigma) and at least 5x better than
  the nominal machine does. The truth is the error set the campaign drew (written in the measurement file's
  comments), not anything identification computed.

A model whose first machine.toml is refused (:data:`REFUSED`) must be refused at load in one line naming the
cause. ``benchmarks/corpus_bench.py`` runs the demo on each.
"""

import json
from pathlib import Path

import numpy as np
import pytest

from pmcal.cli import main
from pmcal.errors import InputError
from pmcal.io_chain import read_measurements
from pmcal.machines import Machine
from tests.test_machine_folder_chain import _truth

CORPUS = Path(__file__).parent / "corpus"
MODELS = sorted(p.name for p in CORPUS.iterdir() if (p / "machine.toml").is_file())

#: models whose first machine.toml is refused at load, with the words the refusal must name (issue 34)
REFUSED = {
    # the 2F-85 finger is underactuated (adaptive): its follower is held by a spring and the joint limits,
    # not by the loop, so the loop leaves it free and it moves the pad's nest
    "robotiq_2f85": ("field 'motors'", "right_follower_joint free"),
}


def test_corpus_has_licences_and_sources():
    assert len(MODELS) >= 2
    for name in MODELS:
        folder = CORPUS / name
        assert (folder / "LICENSE").is_file(), name
        assert "commit" in (folder / "README.md").read_text(), name


@pytest.mark.parametrize("name", MODELS)
def test_corpus_model_loads_and_assembles_at_home(name):
    if name in REFUSED:
        with pytest.raises(InputError) as exc:
            Machine.from_folder(CORPUS / name).twin
        assert all(words in str(exc.value) for words in REFUSED[name])
        return
    machine = Machine.from_folder(CORPUS / name)
    twin = machine.twin
    q = twin.solve(twin.home_commands[None])[0]
    assert np.isfinite(q).all()
    twin._kin(q, jac=False)
    r, _ = twin._closure(None, None, with_jac=False)
    assert np.max(np.abs(r)) < 1e-12                        # m: every loop closed


@pytest.mark.parametrize("name", [n for n in MODELS if n not in REFUSED])
def test_corpus_model_calibrates_on_its_own_twin(name, tmp_path, capsys):
    folder = CORPUS / name
    m_csv, p_json = tmp_path / "m.csv", tmp_path / "p.json"
    assert main(["--machine", str(folder), "twin", "measure", "--poses", "48", "--seed", "3",
                 "-o", str(m_csv)]) == 0
    assert main(["--machine", str(folder), "identify", str(m_csv), "-o", str(p_json)]) == 0
    capsys.readouterr()
    doc = json.loads(p_json.read_text())
    machine = Machine.from_folder(folder)
    twin = machine.twin
    dof = doc["n_poses"] * 3 * twin.n_targets - doc["rank"]
    assert abs(doc["chi2_per_dof"] - 1.0) < 6 * np.sqrt(2.0 / dof)

    truth = _truth(m_csv)
    identified = {k: float(v) for k, v in doc["params"].items()}
    held_out = twin.sample_commands(12, np.random.default_rng(11))
    true_y = twin.targets(held_out, truth)
    pred_y = twin.targets(held_out, identified)
    nominal_y = twin.targets(held_out, None)
    sigma = machine.spec.sigma_mm
    rms = float(np.sqrt(np.mean((pred_y - true_y) ** 2)))
    rms_nominal = float(np.sqrt(np.mean((nominal_y - true_y) ** 2)))
    assert rms < 4 * sigma
    assert rms < rms_nominal / 5
    assert len(read_measurements(str(m_csv), machine.spec).commands) == 48


def test_body_based_closure_sites_can_be_named_in_errors(tmp_path):
    """The Robotiq model closes its four-bars with unnamed body-based connects: the two sites each becomes on
    load are names the machine.toml may list in ``[errors] frames`` (read without MuJoCo), and they are the
    sites the compiled model holds."""
    import shutil

    import mujoco

    from pmcal.mechanism.machine_spec import MachineSpec
    from pmcal.twin.closures import compile_with_site_closures

    folder = tmp_path / "gripper"
    shutil.copytree(CORPUS / "robotiq_2f85", folder)
    toml = folder / "machine.toml"
    toml.write_text(toml.read_text().replace('frames = "all"', 'frames = ["right_driver", "closure0_site1"]'))
    spec = MachineSpec.load(folder)
    assert spec.errors.frames == ("right_driver", "closure0_site1")
    m = compile_with_site_closures(spec.model_path)
    compiled = {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_SITE, i) for i in range(m.nsite)}
    assert {"closure0_site1", "closure0_site2", "closure1_site1", "closure1_site2"} <= compiled


def _edited_copy(tmp_path, name: str, file: str, old: str, new: str) -> Path:
    """A copy of corpus model ``name`` in ``tmp_path`` with ``old`` (asserted present) replaced by ``new`` in its
    ``file``."""
    import shutil

    folder = tmp_path / name
    shutil.copytree(CORPUS / name, folder)
    path = folder / file
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new))
    return folder


def test_a_free_joint_that_moves_the_nests_is_refused_naming_it(tmp_path):
    """Reachy Mini's Stewart platform sits on a turning body (joint yaw_body, actuated). A machine.toml
    without it as a motor leaves the head free to turn: refused at load naming the joint (before the fix its
    own campaign's truth left 1.6 mm rms). The rods' free spin and the antennas, which move no nest, are
    not refused (the corpus machine.toml loads)."""
    yaw = '[[motors]]\njoint = "yaw_body"\nrange = [-10.0, 10.0]\n\n'
    folder = _edited_copy(tmp_path, "reachy_mini", "machine.toml", yaw, "")
    with pytest.raises(InputError) as exc:
        Machine.from_folder(folder).twin
    assert "yaw_body" in str(exc.value) and "machine.toml" in str(exc.value)


@pytest.mark.parametrize("how,words", [
    ("export", "407 mm at closedloop2"),      # every joint at 0: the URDF export's open assembly
    ("rod", "at closedloop2"),                # one achilles-rod hinge 0.01 rad off: a 2.5 mm gap
])
def test_an_open_home_keyframe_is_refused_naming_its_gap(tmp_path, how, words):
    """gepetto_cassie with a ``home`` keyframe that does not close its rods. The twin took any keyframe as
    assembled: at the URDF export's configuration (rod halves 0.36-0.41 m apart) its mobility check judged the
    open assembly and told the user to list the passive joint free_ankle under [[motors]]; a keyframe a little
    open (a hinge 0.01 rad off; the first conversion's welds closed in position and 162 deg off in rotation)
    loaded without a word, its motor values naming no pose of the machine. The keyframe is refused with its
    gap."""
    import re
    import shutil

    folder = tmp_path / "leg"
    shutil.copytree(CORPUS / "gepetto_cassie", folder)
    xml = folder / "gepetto_cassie.xml"
    text = xml.read_text()
    key = re.search(r'<key name="home" qpos="([^"]*)"', text)
    q = np.array(key.group(1).split(), float)
    if how == "export":
        q[:] = 0.0
    else:
        q[Machine.from_folder(CORPUS / "gepetto_cassie").twin.model.joint("tigh_half_hachil_rode_2_rev1").qposadr[0]] \
            += 0.01
    xml.write_text(text.replace(key.group(1), " ".join(repr(float(v)) for v in q)))
    with pytest.raises(InputError) as exc:
        Machine.from_folder(folder).twin
    msg = str(exc.value)
    assert exc.value.field == "keyframe" and "keyframe 'home' does not close the loops" in msg, msg
    assert words in msg and "free_ankle" not in msg, msg


def test_a_home_open_along_a_redundant_closure_equation_is_refused(tmp_path):
    """gepetto_5bar closes its planar loop with a 3-D connect: the out-of-plane equation is redundant, and the
    twin closes the loop along the other two (docs/closed_chain.md, "Over-constraint"). With the closing site
    drawn 1 mm out of the plane, the keyframe leaves that 1 mm gap; the twin found the redundant direction at
    home, took the gap for the joints' play and loaded the drawing without a word (Gepetto's kangaroo_like leg,
    whose robot.yaml closures do not assemble, so loaded with a keyframe 57 mm open). A drawing closes every
    equation at home, as the default configuration must."""
    site = '<site name="closing_1_B" pos="0 -0.46 0.05"'
    folder = _edited_copy(tmp_path, "gepetto_5bar", "gepetto_5bar.xml", site, site.replace("0.05", "0.051"))
    with pytest.raises(InputError) as exc:
        Machine.from_folder(folder).twin
    assert "keyframe 'home' does not close the loops (gap 1 mm at closedloop1)" in str(exc.value)


def test_prediction_covers_a_task_frame_no_nest_sits_on():
    """gepetto_5bar's task site sits on the URDF's fixed `effector` frame, a child body of `end_rod`; the nests
    sit on `end_rod`. The effector frame's six errors move the task and no tracker reading, so no campaign
    identifies them. The prediction propagates the posterior over every error (ChainIdentResult.
    predicted_task_std), so they count with their prior size: seed 1 compensates to 0.24 mm where 0.14 mm is
    predicted (it was 0.0027 mm, 90x off, when only the identifiable errors counted), and identify names
    them (``unseen_by_tracker``). Without those errors (`exclude = ["effector"]`) it gives 0.0042 mm."""
    from pmcal.studies.chain_demo import chain_demo

    demo = chain_demo(Machine.from_folder(CORPUS / "gepetto_5bar"), seed=1)
    s = demo.summary()
    assert s["position_rms_after_mm"] < 3.0 * s["position_rms_predicted_mm"]
    from pmcal.chain import unseen_task_errors
    assert unseen_task_errors(demo.machine, demo.result)


def test_an_error_seen_only_beside_a_motor_zero_is_not_called_unseen():
    """drake_four_bar's coupler offset ``B.dz`` is seen by the nests on the coupler, but only in the
    combination ``A.dry + m1.dzero - 0.014 B.dz``: its own posterior stays at its prior (as an unseen error's
    does), yet the combination is identified and the task point, on the same coupler, sees the same one.
    identify named it 'unseen by the tracker' (a false warning, found on the corpus); the errors of
    gepetto_5bar's effector frame, which no reading moves, are still named."""
    import numpy as np

    from pmcal.chain import campaign, identify, unseen_task_errors

    machine = Machine.from_folder(CORPUS / "drake_four_bar")
    meas, _ = campaign(machine, 48, seed=1)
    res = identify(machine, meas)
    keys = list(res.params)
    prior = machine.twin.prior_std(keys)
    i = keys.index("B.dz")
    assert np.sqrt(res.error_covariance[i, i]) > 0.95 * prior[i], "at its prior, as the warning's first test asks"
    assert "B.dz" not in unseen_task_errors(machine, res)
    assert unseen_task_errors(machine, res) == []


def test_a_barely_seen_combination_that_carries_the_task_error_is_named(tmp_path, capsys):
    """gepetto_delta's task point and its two nests sit on one body, 4-6 mm apart: a rotation of that body about
    the line through the nests moves the task point and barely any reading. On the second simulator's own
    linearised machine (its own parameters, Jacobian and loop solver; benchmarks/crosssim_seed_spread.py) the
    Bayes-optimal compensation leaves 0.0174 mm RMS, almost all of it that direction; measured over 20 seeds,
    0.0173 mm. identify names it (a warning and ``dominant_task_uncertainty``): most of a predicted task error
    of that size, seen at well below one tracker sigma by the 48 poses, with the effector's tilts in it. The
    four-bar, whose task error no barely seen direction dominates, gets no such warning."""
    from benchmarks.crosssim_seed_spread import linear_machine, spread

    folder = CORPUS / "gepetto_delta"
    m_csv, p_json = tmp_path / "m.csv", tmp_path / "p.json"
    assert main(["--machine", str(folder), "twin", "measure", "--poses", "48", "--seed", "2", "-o", str(m_csv)]) == 0
    assert main(["--machine", str(folder), "identify", str(m_csv), "-o", str(p_json)]) == 0
    err = capsys.readouterr().err
    d = json.loads(p_json.read_text())["dominant_task_uncertainty"]
    assert "one combination of errors carries" in err
    assert d["share"] > 0.8 and d["seen_sigma"] < 0.5 and d["unit"] == "mm"
    assert {"eff.dry", "effector.dry"} <= set(d["errors"])
    independent = spread(linear_machine(folder), 400)["bayes_rms"]
    assert 0.75 * independent < d["total"] < 1.33 * independent        # about 1 dof of 400 draws: +-7 %
    four_bar = CORPUS / "drake_four_bar"
    assert main(["--machine", str(four_bar), "twin", "measure", "--poses", "48", "--seed", "2", "-o", str(m_csv)]) == 0
    assert main(["--machine", str(four_bar), "identify", str(m_csv), "-o", str(p_json)]) == 0
    assert "one combination of errors carries" not in capsys.readouterr().err
    assert json.loads(p_json.read_text())["dominant_task_uncertainty"] is None


def test_the_suggested_nest_is_where_a_real_nest_would_see_the_hidden_combination(tmp_path):
    """identify's barely seen combination on gepetto_delta comes with where one more nest would see it
    (``suggested_nest``). The suggestion is checked two ways that do not use its own arithmetic: a site put
    there in the model reads, by the twin's implicit-function derivatives of a real site, what the rigid-body
    field of the suggestion said it would (to 1e-6 mm per unit); and the second simulator's own linearised machine with
    that third nest (its parameters, its Jacobian, its 48-pose plan and held-out targets) leaves a Bayes RMS
    within 35 % of the suggestion's predicted error (8 workspace commands against a 48-pose plan: a few tens
    of percent), a small fraction of the two-nest machine's."""
    import shutil

    from benchmarks.crosssim_seed_spread import linear_machine, spread
    from pmcal.chain import dominant_task_uncertainty, identify

    folder = CORPUS / "gepetto_delta"
    machine = Machine.from_folder(folder)
    m_csv = tmp_path / "m.csv"
    assert main(["--machine", str(folder), "twin", "measure", "--poses", "48", "--seed", "2", "-o", str(m_csv)]) == 0
    result = identify(machine, read_measurements(m_csv, machine.spec))
    d = dominant_task_uncertainty(machine, result, 48)
    nest = d["suggested_nest"]
    assert nest["body"] == "eff" and nest["seen_sigma"] > 3.0 and nest["total"] < 0.25 * d["total"]

    three = tmp_path / "three_nests"
    shutil.copytree(folder, three)
    xml = three / "gepetto_delta.xml"
    x, y, z = (v / 1000.0 for v in nest["position_mm"])
    text = xml.read_text()
    line = next(ln for ln in text.splitlines() if 'name="nest2"' in ln)
    xml.write_text(text.replace(line, line + f'\n<site name="nest3" pos="{x} {y} {z}" size="0.002"/>'))
    toml = three / "machine.toml"
    toml.write_text(toml.read_text().replace('targets = ["nest1", "nest2"]', 'targets = ["nest1", "nest2", "nest3"]'))
    with_nest = Machine.from_folder(three)
    assert with_nest.spec.targets[-1] == "nest3"
    twin, keys = machine.twin, list(result.params)
    commands = twin.sample_commands(6, np.random.default_rng(5))
    body = twin.model.body("eff").id
    field = twin.body_point_jacobian(commands, body, np.array([nest["position_mm"]]), result.params, keys)[:, 0]
    real = with_nest.twin.jacobian(commands, result.params, keys)[:, 2]
    np.testing.assert_allclose(field, real, rtol=0.0, atol=1e-6)

    independent = spread(linear_machine(three), 400)["bayes_rms"]
    two_nests = spread(linear_machine(folder), 400)["bayes_rms"]
    assert 0.65 * independent < nest["total"] < 1.35 * independent
    assert independent < 0.25 * two_nests


def test_transcribed_spherical_manipulator_agrees_with_its_source():
    """rotator_spm was transcribed from the Rotator's kinematics module (JimBlaney/rotator src/rotator/math_utils.py,
    README.md there): pmcal's inverse kinematics of the model gives the servo angles the module's
    ``solve_positions(az, el)`` gives (N, E, S; printed by it to 0.01 deg) for the plate tilted by ``90 - el``
    about the horizontal axis at ``az + 90`` deg (its ``quat_rotation_matrix(-az, el)``)."""
    from scipy.spatial.transform import Rotation

    source = {(0, 70): (-9.51, -7.42, 14.5), (45, 75): (-2.67, -8.39, 1.96), (200, 80): (4.41, 5.33, -3.9),
              (300, 72): (-9.28, 6.15, 11.49), (120, 78): (7.45, -3.72, -6.46)}
    rows = []
    for az, el in source:
        axis = np.array([np.cos(np.radians(90.0 - az)), np.sin(np.radians(90.0 - az)), 0.0])
        R = Rotation.from_rotvec(np.radians(90.0 - el) * axis).as_matrix()
        rz, ry, rx = Rotation.from_matrix(R).as_euler("ZYX", degrees=True)
        rows.append([rx, ry, rz])
    twin = Machine.from_folder(CORPUS / "rotator_spm").twin
    np.testing.assert_allclose(twin.inverse(np.array(rows)), np.array(list(source.values())), atol=0.006)


def test_transcribed_delta_keeps_its_effector_parallel_and_its_exported_pose():
    """haskell_delta was transcribed from an Onshape URDF export (KirkEHaskell/delta-robot-act-vs-diffusion
    hardware/onshape_export/assembly_1/urdf/assembly_1.urdf): at the servo angles of the export (each arm's angle
    below horizontal, the machine.toml's zeros) the task site is the centre of the export's six effector balls
    (its part frame at (26.3128, -99.2005, 224.9328) mm, the balls 9 mm below it), and the three parallelograms
    of ball-jointed rods keep the effector parallel to the base over the motor ranges (a Clavel delta), to the
    export's six-digit rounding (the balls' centres agree to 1.8 um over 46.8 mm pairs: 0.002 deg)."""
    machine = Machine.from_folder(CORPUS / "haskell_delta")
    twin = machine.twin
    exported = np.array([mot.zero for mot in machine.spec.motors])
    np.testing.assert_allclose(twin.forward(exported[None])[0], [26.3128, -99.2005, 215.9328], atol=1e-3)
    eff = twin.model.body("effector").id
    twin._kin(twin.solve(exported[None])[0], jac=False)
    home = twin.data.xmat[eff].reshape(3, 3).copy()
    for q in twin.solve(twin.sample_commands(20, np.random.default_rng(5))):
        twin._kin(q, jac=False)
        turn = np.degrees(np.arccos(np.clip((np.trace(home.T @ twin.data.xmat[eff].reshape(3, 3)) - 1) / 2, -1, 1)))
        assert turn < 0.005                                  # deg


def test_a_planned_pose_the_erroneous_machine_does_not_reach_is_left_out_with_its_name(capsys):
    """A real campaign skips a pose the machine does not reach and measures the rest; so does the twin's campaign
    at explicit commands (the demo's plan, ``twin measure --commands``): the 3-RRR does not close at two of six
    commands (a motor turned 150 deg further), which are left out with a warning naming them, the others measured
    under their own ids. More than half unreachable is an error: the errors do not fit the workspace."""
    from pmcal.chain import campaign
    from pmcal.errors import RunError

    machine = Machine.from_folder(CORPUS / "nopour_3rrr")
    commands = machine.twin.sample_commands(6, np.random.default_rng(0))
    commands[[1, 4]] += 150.0
    meas, _ = campaign(machine, 6, seed=1, commands=commands, pose_id=list("abcdef"))
    assert list(meas.pose_id) == ["a", "c", "d", "f"]
    np.testing.assert_array_equal(meas.commands, commands[[0, 2, 3, 5]])
    assert "2 of the 6 planned poses cannot be assembled" in capsys.readouterr().err.replace("\n", " ")
    commands[[0, 2]] += 150.0
    with pytest.raises(RunError, match="4 of the 6 planned poses"):
        campaign(machine, 6, seed=1, commands=commands)


def test_a_model_without_visible_geometry_is_drawn_as_its_skeleton():
    """reachy_mini's meshes are Git LFS files absent from its source, so its model has no geom: its picture in
    the demo report was black but for three nests (0.04 % of the pixels lit; 6 % now). It is drawn as its kinematic
    skeleton and sites (MuJoCo's autoconnect), and the caption says so."""
    import io

    import matplotlib.image

    from pmcal.twin.render import RenderUnavailable, render_machine_png, visible_moving_geoms

    machine = Machine.from_folder(CORPUS / "reachy_mini")
    assert visible_moving_geoms(machine.twin.model) == 0
    try:
        png = render_machine_png(machine.spec, machine.twin.home_qpos, 320, 200)
    except RenderUnavailable as exc:
        pytest.skip(str(exc))
    pixels = matplotlib.image.imread(io.BytesIO(png))[..., :3]
    lit = np.mean(pixels.max(axis=2) > 0.15)
    assert lit > 0.02, lit
