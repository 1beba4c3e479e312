"""The corpus on a second simulator (tests/crosssim_chain: plain MuJoCo and scipy, its own error
parameterisation and loop solver, nothing of pmcal).

- Without errors both simulators put the nests at the same place at random poses (1e-6 mm; 1e-5 mm for an
  over-constrained loop, :data:`NOMINAL_ATOL`): two loop solvers written apart agree on the nominal machine.
- With random errors of the toml's sizes in the simulator's own parameters (slow): pmcal identifies from the
  simulator's 48-pose campaign (pmcal's plan, 0.01 mm noise) and the compensated commands, driven on the
  simulator, bring the task site within 2x the error pmcal predicts and 20x closer than the nominal IK does
  (:data:`KNOWN_MISSES` excepted).
  ``benchmarks/corpus_crosssim_bench.py`` runs 5 seeds.
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
