"""Closed-form kinematics and error model of the planar robot (paper 003 eq. 1-13), checked against
independent computations: circle geometry, finite differences, and the paper's own tables."""

import numpy as np
import pytest

from pmcal.calib.planar.design import boundary_positions
from pmcal.mechanism.planar.geometry import Errors, Geometry, Workspace
from pmcal.mechanism.planar.kinematics import actual_position, forward, inverse, jacobian
from pmcal.calib.planar.calibration import home_error, position_errors
from pmcal.twin.planar.config import default_machine
from pmcal.apps.planar.study import PAPER

G = Geometry()
W = Workspace()


def grid(n=9):
    x = np.linspace(-W.b / 2, W.b / 2, n)
    y = np.linspace(W.y_lower, W.y_upper, n)
    return np.stack(np.meshgrid(x, y), -1).reshape(-1, 2)


def test_home_position_is_the_circle_intersection():
    # P0: B1 = (455, 0), B2 = (-455, 0); P below at sqrt(l^2 - 455^2)
    p0 = forward(G, G.home)
    assert p0 == pytest.approx([0.0, -np.sqrt(825.0**2 - 455.0**2)], abs=1e-9)
    assert inverse(G, p0) == pytest.approx(G.home, abs=1e-12)


def test_ik_satisfies_the_loop_equation_and_fk_inverts_it():
    r = grid()
    th = inverse(G, r)
    B = G.e + G.L[:, None] * np.stack([np.cos(th), np.sin(th)], -1)
    # eq. 1: |r - B_i| = l_i for both limbs
    assert np.abs(np.linalg.norm(r[:, None, :] - B, axis=-1) - G.l).max() < 1e-9
    assert np.abs(forward(G, th) - r).max() < 1e-9
    # assembly mode of the paper's robot: elbows outwards, theta1 near 0 and theta2 near 180 deg
    assert np.all(np.abs(th[:, 0]) < np.deg2rad(60)) and np.all(np.abs(th[:, 1] - np.pi) < np.deg2rad(60))


def test_unreachable_positions_give_nan():
    assert np.all(np.isnan(inverse(G, np.array([0.0, -1300.0]))))


@pytest.mark.parametrize("model", ["simplified", "full"])
def test_error_transfer_matrix_matches_finite_differences(model):
    """Eq. 12-13 against central differences of the exact kinematics with perturbed parameters."""
    r = grid(4)
    J = jacobian(G, r, model)
    th = inverse(G, r)
    h = 1e-5
    names = (["dtheta1", "dtheta2"] if model == "simplified"
             else ["dtheta1", "de1x", "de1y", "dL1", "dl1", "dtheta2", "de2x", "de2y", "dL2", "dl2"])
    for col, key in enumerate(names):
        scale = G.L[0] if key == "dtheta1" else G.L[1] if key == "dtheta2" else 1.0
        plus = actual_position(G, Errors.from_internal({key: h / scale}), th)
        minus = actual_position(G, Errors.from_internal({key: -h / scale}), th)
        fd = (plus - minus) / (2 * h)
        assert np.abs(fd - J[..., col]).max() < 1e-6, key


def test_position_errors_before_calibration_equal_paper_tables_3_and_4():
    """Δp0 (Table 3) and Δp_max at the six positions (Table 4) before calibration: pure kinematics of
    paper Tables 1-2. Agreement to the printed digits fixes the frame (y up, c = (0,-79), d = (0,-51)) and
    the sign convention of the zero offsets (real angle = commanded + Δθ)."""
    machine = default_machine()
    r6 = boundary_positions(W, 3)
    for grp in PAPER["table3"]:
        err = machine.preset(grp)
        assert home_error(G, err) == pytest.approx(PAPER["table3"][grp][4], abs=2e-3), grp
        assert position_errors(G, err, r6).max() == pytest.approx(PAPER["table4"][grp][0], abs=1e-3), grp
