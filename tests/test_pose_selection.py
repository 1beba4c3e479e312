"""Pose selection by D-optimality and condition number (calib/pose_selection.py)."""

import numpy as np
import pytest

from pmcal.calib.ocpm import paper_model as pm
from pmcal.calib.pose_selection import condition_number, crlb_std, select_poses
from pmcal.twin.ocpm.campaign import plan_orientations


def test_d_optimal_straight_line_puts_poses_at_the_ends():
    """Fitting y = a + b t on distinct candidates t in [-1, 1]: the D-optimal 6-point design maximises
    det = 6 sum t^2 - (sum t)^2, i.e. the three most extreme candidates at each end."""
    t = np.linspace(-1, 1, 41)
    blocks = np.stack([np.ones_like(t), t], axis=1)[:, None, :]
    idx = select_poses(blocks, 6, "D")
    np.testing.assert_allclose(np.sort(t[idx]), [-1, -0.95, -0.9, 0.9, 0.95, 1])


def test_selection_beats_random_on_the_seed_model():
    rng = np.random.default_rng(0)
    phi, theta = plan_orientations(400, 60.0, rng)
    names = [k for k in pm.param_names() if k not in ("L1.day", "L2.dax")]
    B = pm.design_blocks(np.deg2rad(phi), np.deg2rad(theta), names)
    d_opt = select_poses(B, 24, "D")
    c_opt = select_poses(B, 24, "condition")
    rand = [rng.choice(400, 24, replace=False) for _ in range(50)]
    cond_rand = np.median([condition_number(B, i) for i in rand])
    assert condition_number(B, c_opt) <= condition_number(B, d_opt) < cond_rand / 2
    logdet = lambda i: np.linalg.slogdet(np.einsum("kci,kcj->ij", B[i], B[i]))[1]  # noqa: E731
    assert logdet(d_opt) > max(logdet(i) for i in rand)
    assert np.max(crlb_std(B, d_opt)) < np.median([np.max(crlb_std(B, i)) for i in rand])
    assert len(set(d_opt)) == 24


def test_bad_requests():
    B = np.ones((5, 1, 2))
    with pytest.raises(ValueError, match="cannot choose"):
        select_poses(B, 6)
    with pytest.raises(ValueError, match="unknown criterion"):
        select_poses(B, 2, "A")


def test_prior_information_steers_the_choice_to_what_is_not_known():
    """Straight line y = a + b x: without a prior the D-optimal pair is the two ends of the range; with
    the intercept known (a strong prior on it) D-optimality is max sum x^2, the two largest |x|."""
    from pmcal.calib.pose_selection import select_poses

    x = np.array([-1.0, -0.5, 0.0, 0.5, 1.0, 2.0, 2.5, 3.0])
    blocks = np.stack([np.ones_like(x), x], axis=-1)[:, None, :]      # (N, 1 row, 2 params)
    assert list(select_poses(blocks, 2, "D")) == [0, 7]
    assert list(select_poses(blocks, 2, "D", prior=np.diag([1e6, 0.0]))) == [6, 7]
