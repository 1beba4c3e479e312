"""Closed-form kinematics of the over-constrained PM against independent computations."""

import numpy as np
import pytest
from scipy.optimize import brentq

from pmcal.mechanism.ocpm.config import default_geometry
from pmcal.mechanism.ocpm.kinematics import (HOME_BETA, limb_ik, nominal_fk, nominal_ik, nominal_pose,
                                   real_ik_commands)
from pmcal.mechanism.ocpm.params import ErrorSet, random_errors
from pmcal.mechanism.rotations import rot_x, rot_y, rot_z, tilt_torsion, tilt_torsion_angles

G = default_geometry()


def random_orientations(n, theta_max_deg=80.0, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(0, 2 * np.pi, n), np.deg2rad(rng.uniform(0.5, theta_max_deg, n))


def test_tilt_torsion_matches_seed_eq4_elementwise():
    phi, theta = random_orientations(50)
    c, s, ct, st = np.cos(phi), np.sin(phi), np.cos(theta), np.sin(theta)
    eq4 = np.array([[c**2 * ct + s**2, s * c * ct - s * c, c * st],
                    [s * c * ct - s * c, s**2 * ct + c**2, s * st],
                    [-c * st, -s * st, ct]]).transpose(2, 0, 1)
    assert np.abs(tilt_torsion(phi, theta) - eq4).max() < 1e-15


def test_eq17_reads_back_the_angles():
    phi, theta = random_orientations(200)
    p2, t2 = tilt_torsion_angles(tilt_torsion(phi, theta))
    assert np.abs(t2 - theta).max() < 1e-12
    assert np.abs(np.angle(np.exp(1j * (p2 - phi)))).max() < 1e-10


def test_elementary_rotations_are_right_handed():
    e = np.eye(3)
    assert np.allclose(rot_z(np.pi / 2) @ e[0], e[1])
    assert np.allclose(rot_x(np.pi / 2) @ e[1], e[2])
    assert np.allclose(rot_y(np.pi / 2) @ e[2], e[0])


def test_nominal_machine_mirror_symmetry_oracle():
    """On the nominal machine every S_j lies on the plane bisecting O-C_E and on the platform
    revolute's plane (docs/ocpm_2dof.md: the test oracle of any nominal model)."""
    phi, theta = random_orientations(300)
    r, R = nominal_pose(phi, theta)
    ik = limb_ik(r, R, limbs=(1, 2, 3, 4))
    assert np.isfinite(ik.beta).all()
    n = r / np.linalg.norm(r, axis=1, keepdims=True)
    mid = 0.5 * r
    assert np.abs(np.einsum("nkj,nj->nk", ik.S - mid[:, None], n)).max() < 1e-9
    assert np.abs(ik.planarity).max() < 1e-9
    assert np.abs(np.linalg.norm(ik.S - ik.A, axis=-1) - G.l).max() < 1e-9
    assert np.abs(np.linalg.norm(ik.S - G.base_points()[None], axis=-1) - G.l).max() < 1e-9


def test_home_angle_matches_the_spec():
    assert HOME_BETA == pytest.approx(-39.351, abs=5e-4)


def test_real_ik_solves_eq12_against_a_bracketing_root_finder():
    """beta from the closed form (eq. 13) equals a numerical root of |B + L1 w1(beta) - A| = L2."""
    rng = np.random.default_rng(3)
    e = ErrorSet.from_dict(random_errors(rng, 1.5, 0.3))
    phi, theta = random_orientations(40, 70, seed=4)
    r, R = nominal_pose(phi, theta)
    ik = limb_ik(r, R, e, limbs=(1, 2, 3, 4))
    for j in range(4):
        Q = rot_z(G.psi[j]) @ rot_z(e.dgamma[j]) @ rot_x(e.dalpha[j])
        B = G.base_points()[j] + e.db[j]
        L1, L2 = G.l + e.dl1[j], G.l + e.dl2[j]
        for i in range(len(phi)):
            A = r[i] + R[i] @ (G.platform_points()[j] + e.da[j])
            f = lambda b: np.linalg.norm(B + L1 * Q @ np.array([np.cos(b), 0, -np.sin(b)]) - A) - L2
            b0 = ik.beta[i, j]
            root = brentq(f, b0 - 0.2, b0 + 0.2, xtol=1e-14)
            assert abs(root - b0) < 1e-10
            assert abs(f(b0)) < 1e-9


def test_population_axis_matches_single_evaluations():
    rng = np.random.default_rng(5)
    sets = [ErrorSet.from_dict(random_errors(rng, 1.0, 0.2)) for _ in range(4)]
    stacked = ErrorSet(**{k: np.stack([np.asarray(getattr(s, k), float) for s in sets])
                          for k in ErrorSet.__dataclass_fields__})
    r, R = nominal_pose(*random_orientations(30))
    pop = limb_ik(r, R, stacked)
    for p, s in enumerate(sets):
        assert np.array_equal(pop.beta[p], limb_ik(r, R, s).beta)


def test_nominal_fk_inverts_nominal_ik():
    phi, theta = random_orientations(500, 80)
    ph, th = nominal_fk(nominal_ik(phi, theta))
    assert np.abs(th - theta).max() < 1e-11
    assert np.abs(np.angle(np.exp(1j * (ph - phi))) * np.sin(theta)).max() < 1e-11


def test_zero_offset_enters_commands_with_a_minus_sign():
    e = ErrorSet.from_dict({"L1.dtheta": 0.25, "L2.dtheta": -0.4})
    r, R = nominal_pose(*random_orientations(10))
    cmd = real_ik_commands(r, R, e)
    beta = limb_ik(r, R).beta
    assert np.allclose(np.rad2deg(beta - cmd), [0.25, -0.4], atol=1e-12)
