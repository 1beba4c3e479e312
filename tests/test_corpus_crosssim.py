"""The corpus on a second simulator (tests/crosssim_chain: plain MuJoCo and scipy, its own error
parameterisation and loop solver, nothing of pmcal).

- Without errors both simulators put the nests at the same place at random poses (1e-6 mm; 1e-5 mm for an
  over-constrained loop, :data:`NOMINAL_ATOL`): two loop solvers written apart agree on the nominal machine.
- With random errors of the toml's sizes in the simulator's own parameters (slow): pmcal identifies from the
  simulator's 48-pose campaign (pmcal's plan, 0.01 mm noise) and the compensated commands, driven on the
  simulator, bring the task site within 2x the error pmcal predicts and 20x closer than the nominal IK does
  (:data:`KNOWN_MISSES` excepted).
  ``benchmarks/corpus_crosssim_bench.py`` runs 5 seeds.
- The benchmark's reference (tests/crosssim_chain/reference.py: a plain least-squares fit in the simulator's own
  errors): its implicit-function Jacobian equals finite differences through the simulator's closure where the
  loops close; on a noise-free campaign whose errors lie in the fitted row space it reproduces the nests and its
  compensation puts the true simulator's task on the targets. Its Bayes variant (every error with the
  simulator's own prior) is the linear posterior mean in the linear regime.
"""

import numpy as np
import pytest

from pmcal.machines import Machine
from tests.crosssim_chain.machine import SimMachine
from tests.test_corpus import CORPUS, MODELS, REFUSED

CALIBRATED = [n for n in MODELS if n not in REFUSED]         # the corpus models pmcal accepts

#: mm: where the two simulators' over-constraint rules part on the nominal machine (default 1e-6). The
#: ToddlerBot neck's tilt rods are not an exact parallelogram (their lengths differ by 0.05 mm in the CAD): its
#: second rod is over-constrained away from home, pmcal closes it along the directions independent at home,
#: the second simulator by least squares; they part by 4e-6 mm on the nests
NOMINAL_ATOL = {"toddlerbot_neck": 1e-5}


@pytest.mark.parametrize("name", CALIBRATED)
def test_second_simulator_agrees_on_the_nominal_machine(name):
    machine = Machine.from_folder(CORPUS / name)
    commands = machine.twin.sample_commands(4, np.random.default_rng(2))
    sim = SimMachine(CORPUS / name)
    np.testing.assert_allclose(sim.nests(commands), machine.twin.targets(commands, None), rtol=0,
                               atol=NOMINAL_ATOL.get(name, 1e-6))


#: corpus models whose calibration on the second simulator's data cannot improve the task 20-fold (issue 34)
KNOWN_MISSES = {
    # the task site sits on the URDF's `effector` frame, a child body of `end_rod` that no nest sits on: its six
    # frame errors move the task and no tracker reading, so no calibration corrects them (identify names them,
    # ``unseen_by_tracker``, and the prediction counts them at their prior: within 2x of what is reached); the
    # improvement is then 10-55x, not 20x on every seed (seed 1: 2.4 -> 0.24 mm)
    "gepetto_5bar": "the task frame's own errors are invisible to the nests: no calibration corrects them",
}


@pytest.mark.slow
@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.xfail(reason=KNOWN_MISSES[n], strict=True))
                                  if n in KNOWN_MISSES else n for n in CALIBRATED])
def test_calibration_on_the_second_simulators_data(name, tmp_path):
    from benchmarks.corpus_crosssim_bench import run

    r = run(CORPUS / name, 1, tmp_path)
    assert r["stage"] == "done" and r["identify_exit"] == 0
    fam = "position_%s_mm" if "position_after_mm" in r else "orientation_%s_deg"   # an orientation-only task
    assert r[fam % "after"] < 2.0 * r[fam % "predicted"]
    assert r[fam % "after"] < r[fam % "before"] / 20


@pytest.mark.parametrize("name", CALIBRATED)
def test_second_simulator_moves_every_closure_site(name):
    """The second simulator draws position errors for every site a site-based closure (connect or weld) uses,
    as pmcal does (`[errors] frames = "all"`). A weld-aware rewrite once compared MuJoCo's equality enums with
    ``in`` against numpy integers, dropped every closing site of every model and changed the simulated
    machines (reachy_mini's first nest moved by 0.37 mm at the same seed)."""
    import mujoco

    sim = SimMachine(CORPUS / name)
    m = sim.model
    sites = {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_SITE, int(i))
             for e in range(m.neq) if m.eq_objtype[e] == mujoco.mjtObj.mjOBJ_SITE
             and m.eq_type[e] != mujoco.mjtEq.mjEQ_JOINT for i in (m.eq_obj1id[e], m.eq_obj2id[e])}
    assert all(f"{s}/{c}" in sim.error_keys for s in sites for c in ("tx", "ty", "tz"))


def test_reference_jacobian_is_the_closures_derivative():
    """Reachy Mini (loops that close): d nests / d error by the implicit-function step against central
    differences through the simulator's own closure (warm-started), body, site and motor-zero errors. The
    closure converges to 1e-7 mm; over a 2e-3 step that leaves 1e-4 per unit."""
    from tests.crosssim_chain import reference

    name = "reachy_mini"
    machine = Machine.from_folder(CORPUS / name)
    commands = machine.twin.sample_commands(2, np.random.default_rng(3))
    sim0 = SimMachine(CORPUS / name)
    sim = SimMachine(CORPUS / name, sim0.random_errors(np.random.default_rng(4)))
    qs = sim.solve(commands)
    assert not reference.over_constrained(sim, qs)
    keys = [k for k in sim.error_keys if k.endswith(("/tx", "/ey", "/zero"))][::7]
    assert any(k.endswith("/zero") for k in keys) and len(keys) >= 6
    J = reference.jacobian(sim, qs, keys)
    h = reference.H_PARAM
    for c, key in enumerate(keys):
        out = []
        for s in (1.0, -1.0):
            v = reference.variant(sim, {**sim.errors, key: sim.errors.get(key, 0.0) + s * h})
            out.append(np.array([reference._outputs(v, q, "nests")[1] for q in reference.close_from(v, qs, commands)]))
        np.testing.assert_allclose(J[:, c], ((out[0] - out[1]) / (2 * h)).ravel(), rtol=0, atol=1e-4, err_msg=key)


def test_reference_fit_recovers_noise_free_errors():
    """The five-bar (an over-constrained loop: the polish step's path too), 12 poses, no noise, true errors of
    the toml's sizes projected on the row space the fit works in (what nests at noise 0.01 mm determine): the
    plain least squares reproduces the nests (1e-6 mm, against 0.01 mm noise) and the targets compensated with
    it are reached on the true simulator within 1e-4 mm (the errors it leaves at zero move no nest by as much as
    the noise; their projection removed, nothing is left)."""
    from pmcal.chain import sample_targets
    from pmcal.mechanism.task_space import task_difference
    from tests.crosssim_chain import reference

    name = "gepetto_5bar"
    machine = Machine.from_folder(CORPUS / name)
    sigma = machine.spec.sigma_mm
    commands = machine.twin.sample_commands(12, np.random.default_rng(5))
    sim0 = SimMachine(CORPUS / name)
    keys, s = sim0.error_keys, reference.sizes(sim0)
    J0 = reference.jacobian(sim0, sim0.solve(commands), keys) * s
    _, sv, Vt = np.linalg.svd(J0, full_matrices=False)
    V = Vt[sv >= sigma].T
    assert 0 < V.shape[1] < len(keys)
    u = V @ (V.T @ np.random.default_rng(6).normal(size=len(keys)))
    sim = SimMachine(CORPUS / name, dict(zip(keys, s * u)))
    qs = sim.solve(commands)
    nests = np.array([sim._sites(q, sim.target_ids) for q in qs])
    ref = reference.fit(sim0, commands, nests, qs, sigma)
    assert ref["rank"] == V.shape[1]
    assert ref["rms_residual_mm"] < 1e-6
    targets = sample_targets(machine, 4, seed=7)
    nominal = machine.twin.inverse(targets, None)
    q_nominal = sim.solve(nominal)
    before = task_difference(sim.task(nominal), targets, sim.coordinates)
    assert np.abs(before).max() > 0.1                           # the errors move the task: a real check
    cmd = reference.inverse(reference.variant(sim0, ref["errors"]), targets, nominal, q_nominal)
    assert np.abs(task_difference(sim.task(cmd), targets, sim.coordinates)).max() < 1e-4


def test_bayes_reference_is_the_posterior_mean():
    """The benchmark's Bayes reference (``reference.fit(prior=True)``: every error of the simulator with its own
    prior): on an 8-pose noisy campaign of the four-bar with errors a tenth of the toml's sizes (the linear
    regime), the fitted errors equal the linear posterior mean ``(A'A + I)^-1 A'y`` computed here from the
    simulator's Jacobian (to 1e-3 prior sizes, against errors of 0.1), and they differ from the truncated plain
    fit in the directions it leaves at zero: the prior, not the truncation, sets them."""
    from tests.crosssim_chain import reference

    name = "drake_four_bar"
    machine = Machine.from_folder(CORPUS / name)
    sigma = machine.spec.sigma_mm
    rng = np.random.default_rng(11)
    commands = machine.twin.sample_commands(8, rng)
    sim0 = SimMachine(CORPUS / name)
    keys, s = sim0.error_keys, reference.sizes(sim0)
    q0 = sim0.solve(commands)
    A = reference.jacobian(sim0, q0, keys, commands=commands) * s / sigma
    sim = SimMachine(CORPUS / name, dict(zip(keys, 0.1 * s * rng.normal(size=len(keys)))))
    qs = sim.solve(commands)
    noise = rng.normal(0.0, sigma, (len(qs), len(sim.target_ids), 3))
    nests = np.array([sim._sites(q, sim.target_ids) for q in qs]) + noise
    y = (nests.ravel() - np.array([sim0._sites(q, sim0.target_ids) for q in q0]).ravel()) / sigma
    expected = np.linalg.solve(A.T @ A + np.eye(len(keys)), A.T @ y)
    fitted = reference.fit(sim0, commands, nests, qs, sigma, max_nfev=6, prior=True)["errors"]
    bayes = np.array([fitted[k] for k in keys]) / s
    np.testing.assert_allclose(bayes, expected, rtol=0, atol=1e-3)
    fitted = reference.fit(sim0, commands, nests, qs, sigma, max_nfev=6)["errors"]
    plain = np.array([fitted[k] for k in keys]) / s
    assert np.max(np.abs(bayes - plain)) > 0.01
