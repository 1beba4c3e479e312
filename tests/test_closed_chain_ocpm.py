"""The generic closed-chain core on the seeded over-constrained machine (ocpm_2dof's MJCF described as data,
with compliant closures) against the machine's own, separately written twin (pmcal.twin.ocpm.machine.Twin)."""

import numpy as np
import pytest

from pmcal.mechanism.ocpm.params import random_errors
from pmcal.mjcf import machine_dir
from pmcal.twin.closed_chain import ClosedChainTwin
from pmcal.twin.ocpm.machine import Twin

@pytest.fixture(scope="module")
def folder():
    return machine_dir("ocpm_2dof") / "chain"        # the seeded machine's MJCF, described as data


CMD = np.array([[-30.0, -45.0], [-60.0, -20.0], [-10.0, -70.0], [-39.35, -39.35], [-80.0, -5.0]])


def test_structure(folder):
    twin = ClosedChainTwin.from_folder(folder)
    assert len(twin.passive) == 12 and twin.n_equations == 12      # square, but over-constrained
    assert len(twin._spring_dof) == 1                               # ss_slide
    assert "closure_S1" in [c.name for c in twin.closures]


@pytest.mark.parametrize("seed", [None, 3, 4])
def test_matches_the_dedicated_compliant_twin(folder, seed):
    """Same MJCF with the dedicated twin's errors written in (its own apply_errors: bodies, sites, the ball
    anchor), motor zero offsets as m1/m2.dzero: the generic least-squares equilibrium is the dedicated
    quasi-static one."""
    errors = None if seed is None else random_errors(np.random.default_rng(seed))
    ded = Twin(errors)
    state = ded.reach(CMD)
    spec = ClosedChainTwin.from_folder(folder).spec
    gen = ClosedChainTwin(spec, model=ded.model)
    zero = {} if errors is None else {"m1.dzero": errors.get("L1.dtheta", 0.0), "m2.dzero": errors.get("L2.dtheta", 0.0)}
    assert state.converged.all()
    np.testing.assert_allclose(gen.targets(CMD, zero), state.targets, atol=1e-9)    # mm
