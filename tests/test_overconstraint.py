"""Over-constraint in the generic core: a planar five-bar closed by a 3-D connect (tests/data/fivebar) has
one redundant closure equation (out of the plane), found from the closure Jacobian's rank, and the twin
closes the loop along the other two only (pmcal.twin.overconstraint).

The reference is a closed form of the real machine written here, not from pmcal: a planar five-bar whose
cranks, links, hinge positions and motor zeros carry errors of its own parameterisation (in the plane; the
nests' coordinates on their part are known, as from a CMM); an out-of-plane tilt of a hinge does not move the tool in
the plane (the real joints' play takes the strain). On its data, pmcal's identification with every frame
error considered (``frames = "all"``, out-of-plane tilts included) compensates the machine to within 1.5x of
a plain least-squares fit in the closed form's own parameters, and an identified tilt stays near its prior.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import least_squares

from pmcal.chain import compensate, plan
from pmcal.calib.closed_chain import identify_chain
from pmcal.machines import Machine
from pmcal.twin.overconstraint import loop_redundancy, loop_summary
from tests.chain_references import FIVEBAR

CORPUS = Path(__file__).parent / "corpus"

SIGMA = 0.005                                  # mm, the toml's tracker noise
#: the closed form's own parameters (mm, deg) and their sizes on the test machines
OWN = {"lx": 0.1, "ly": 0.1, "rx": 0.1, "ry": 0.1, "lc": 0.1, "rc": 0.1, "ll": 0.1, "lp": 0.1, "rl": 0.1,
       "lz": 0.05, "rz": 0.05}


def _turn(v: np.ndarray, angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1]], 1)


def closed_form(theta_deg: np.ndarray, e: dict) -> tuple[np.ndarray, np.ndarray]:
    """Tool and SMR (N, 3) mm of the five-bar with errors ``e`` (keys of :data:`OWN`; missing 0) at motor
    angles (N, 2) deg: hinges at (-+100 + lx/rx, ly/ry), cranks of 200 + lc/rc turned by the motor angle
    plus its zero error lz/rz (counter-clockwise about +z from +y); the left link's closing hinge at
    (223.6 + ll along, lp across) in the left link's part frame (origin at its crank hinge), the right one
    223.6 + rl from its crank hinge; they meet at the upper circle intersection. The tool and the SMR sit
    where the drawing puts them on the left link's part (the nests' coordinates are known: 223.6 mm along
    the part's axis, 20 mm high; halfway, 10 mm high)."""
    g = lambda k: float(e.get(k, 0.0))                                     # noqa: E731
    t = np.deg2rad(np.atleast_2d(theta_deg) + [g("lz"), g("rz")])
    c, lk = FIVEBAR["crank"], FIVEBAR["link"]
    a = np.stack([-FIVEBAR["base"] + g("lx") - (c + g("lc")) * np.sin(t[:, 0]), g("ly") + (c + g("lc")) * np.cos(t[:, 0])], 1)
    b = np.stack([FIVEBAR["base"] + g("rx") - (c + g("rc")) * np.sin(t[:, 1]), g("ry") + (c + g("rc")) * np.cos(t[:, 1])], 1)
    la, lb = np.hypot(lk + g("ll"), g("lp")), lk + g("rl")
    d = np.linalg.norm(b - a, axis=1)
    u = (b - a) / d[:, None]
    x = (d ** 2 + la ** 2 - lb ** 2) / (2 * d)
    h = np.sqrt(la ** 2 - x ** 2)
    meet = a + x[:, None] * u + h[:, None] * np.stack([-u[:, 1], u[:, 0]], 1)
    axis = _turn((meet - a) / la, -np.arctan2(g("lp"), lk + g("ll")))     # the left part's own axis
    z = np.ones(len(t))
    return np.c_[a + lk * axis, 20 * z], np.c_[a + lk / 2 * axis, 10 * z]


def _readings(theta: np.ndarray, e: dict) -> np.ndarray:
    tool, smr = closed_form(theta, e)
    return np.stack([tool, smr], axis=1)                                   # (N, 2, 3) as the toml's targets


@pytest.fixture(scope="module")
def fivebar(tmp_path_factory):
    folder = tmp_path_factory.mktemp("oc") / "fivebar"
    shutil.copytree("tests/data/fivebar", folder)
    toml = folder / "machine.toml"
    toml.write_text(toml.read_text() + '\n[errors]\nframes = "all"\nposition_mm = 0.1\nangle_deg = 0.1\n'
                    'zero_deg = 0.05\n')
    return Machine.from_folder(folder)


def test_the_out_of_plane_closure_equation_is_redundant(fivebar):
    red = loop_redundancy(fivebar.twin)
    assert red.n_equations == 3 and red.redundant == 1
    assert red.described == ["tip z (100% of it)"]
    # tilts of the hinges and heights of the closure sites only strain the loop; in-plane errors do not
    assert {"left_crank.drx", "right_link.dry", "left_tip.dz"} <= set(red.strain_errors)
    assert not {"left_crank.dx", "right_link.drz", "left_tip.dy"} & set(red.strain_errors)
    assert loop_summary(fivebar.twin) == {"closure_equations": 3, "independent": 2, "redundant": ["tip z (100% of it)"]}
    delta = Machine.builtin("delta_3dof").twin
    assert loop_summary(delta) == {"closure_equations": 18, "independent": 18, "redundant": []}


def test_a_tilt_moves_the_tool_as_the_tilted_part_does(fivebar):
    """The twin with a tilt t of the left crank's hinge: the loop still closes along its independent
    directions (the joints' play takes the out-of-plane gap), and the tool, 20 mm above the closing hinge on
    the tilted link, moves in the plane by what the tilt does to it, 20 mm sin t (0.1745 mm at 0.5 deg), to
    first order. What is left is of second order in the tilt (below 0.2 mm t^2, t in deg: 0.0014 mm at the
    prior's 0.1 deg): the redundant directions follow the tilted loop (the closure Jacobian's smallest
    singular directions at each pose), so the gap's in-plane part the tilt makes is the joints' to close, as
    on a least-squares closure. No first-order effect in the plane: a tilt cannot stand in for an in-plane
    error in identification (it has no effect there and is left out)."""
    twin = fivebar.twin
    cmd = np.random.default_rng(2).uniform(-30.0, 30.0, size=(20, 2))
    flat = twin.targets(cmd)
    excess = {}
    for t in (0.1, 0.5):
        tilted = twin.targets(cmd, {"left_crank.drx": t})
        assert np.isfinite(tilted).all()
        shift = np.linalg.norm(tilted[:, 0, :2] - flat[:, 0, :2], axis=1)
        excess[t] = shift - 20.0 * np.sin(np.deg2rad(t))
        assert np.all(excess[t] > -0.008 * t) and np.all(excess[t] < 0.2 * t ** 2), (t, excess[t])
    # second order: five times the tilt, about 25 times the excess (not 5, a first-order term's)
    assert np.median(excess[0.5] / excess[0.1]) > 15.0


def _plain_fit(theta: np.ndarray, y: np.ndarray) -> dict:
    """Least squares in the closed form's own parameters (every one, from zero): the reference fit."""
    keys = list(OWN)
    res = least_squares(lambda x: (_readings(theta, dict(zip(keys, x))) - y).ravel() / SIGMA,
                        np.zeros(len(keys)), x_scale=np.array(list(OWN.values())), method="lm")
    return dict(zip(keys, res.x))


def _ik(task: np.ndarray, e: dict, start: np.ndarray) -> np.ndarray:
    """Motor angles (N, 2) that put the closed form's tool on ``task`` (N, 2) mm, Newton from ``start``."""
    out = []
    for p, q0 in zip(task, start):
        sol = least_squares(lambda q: closed_form(q[None], e)[0][0, :2] - p, q0, method="lm", xtol=1e-14)
        out.append(sol.x)
    return np.array(out)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_identification_against_the_closed_form_of_the_real_machine(fivebar, seed):
    rng = np.random.default_rng(seed)
    truth = {k: float(rng.normal(0.0, s)) for k, s in OWN.items()}
    design = plan(fivebar, 48, seed=seed)
    theta = design.commands
    y = _readings(theta, truth) + rng.normal(0.0, SIGMA, size=(len(theta), 2, 3))
    res = identify_chain(fivebar.twin, theta, y, SIGMA)
    assert 0.7 < res.chi2_per_dof < 1.3, res.chi2_per_dof
    # no out-of-plane tilt is driven beyond 3 sigma of its prior to absorb an in-plane effect
    tilts = [k for k in res.base if k.endswith((".drx", ".dry"))]
    sizes = dict(zip(res.base, fivebar.twin.prior_std(res.base)))
    assert all(abs(res.params[k]) < 3 * sizes[k] for k in tilts), {k: res.params[k] for k in tilts}
    task = fivebar.twin.forward(fivebar.twin.sample_commands(30, np.random.default_rng(100 + seed)))
    nominal = fivebar.twin.inverse(task)
    before = np.linalg.norm(closed_form(nominal, truth)[0][:, :2] - task, axis=1)
    after = np.linalg.norm(closed_form(compensate(fivebar, res.params, task), truth)[0][:, :2] - task, axis=1)
    plain = np.linalg.norm(closed_form(_ik(task, _plain_fit(theta, y), nominal), truth)[0][:, :2] - task, axis=1)
    rms = lambda v: float(np.sqrt(np.mean(v ** 2)))                      # noqa: E731
    assert rms(before) > 0.1
    assert rms(after) < 1.5 * rms(plain) + 0.001, (rms(before), rms(after), rms(plain))


def test_redundant_loops_close_as_well_as_the_joints_can_wherever_the_machine_is():
    """ToddlerBot's neck (tests/corpus: a parallelogram of two rods, 8 redundant closure equations) with
    random errors of its machine.toml's sizes. The loops are closed along their independent directions at
    each configuration (followed from home to that pose and those errors), so

    - the gap left has no part along the directions the passive joints close: checked on plain MuJoCo,
      the closure sites' distance vectors and their passive Jacobians (``mj_jacSite``) at the assembled
      poses (with home's directions, fixed in the world while the neck pans, 0.2 mm of the gap at other
      poses was the joints' to close);
    - forward and inverse kinematics agree: the commands the inverse finds for a target put the task there
      (it was 0.005-0.015 deg off, more than the machine's calibration predicts, 0.003 deg).
    """
    import mujoco

    from pmcal.chain import random_errors, sample_targets
    from pmcal.mechanism.task_space import task_difference

    machine = Machine.from_folder(CORPUS / "toddlerbot_neck")
    twin = machine.twin
    assert len(twin.redundant_directions) == 8
    coords = machine.spec.task.coordinates
    for seed in (1, 2):
        truth = random_errors(machine, np.random.default_rng(seed))
        task = sample_targets(machine, 8, seed=seed + 1000)
        cmd = twin.inverse(task, truth)
        assert np.isfinite(cmd).all()
        assert np.abs(task_difference(twin.forward(cmd, truth), task, coords)).max() < 1e-9      # deg
        q = twin.solve(cmd, truth)                   # the model now holds these errors (twin.set_params)
        m, d = twin.model, mujoco.MjData(twin.model)
        motor_dofs = {int(m.jnt_dofadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, mot.joint)])
                      for mot in machine.spec.motors}
        passive = [v for v in range(m.nv) if v not in motor_dofs]
        for qi in q:
            d.qpos[:] = qi
            mujoco.mj_forward(m, d)
            gap, jac = [], []
            for c in twin.closures:
                j1, j2 = np.zeros((3, m.nv)), np.zeros((3, m.nv))
                mujoco.mj_jacSite(m, d, j1, None, c.site1)
                mujoco.mj_jacSite(m, d, j2, None, c.site2)
                gap.append(d.site_xpos[c.site1] - d.site_xpos[c.site2])
                jac.append(j1 - j2)
            gap, jac = np.concatenate(gap), np.concatenate(jac)[:, passive]
            assert np.linalg.norm(gap) > 1e-6            # m: the errors strain the loops (it is a real test)
            U = np.linalg.svd(jac, full_matrices=True)[0][:, : len(gap) - 8]    # what the joints can close
            assert np.linalg.norm(U.T @ gap) < 1e-10     # m (the solver meets 1e-12 per equation; gap ~0.5 mm)
