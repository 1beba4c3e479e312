"""Over-constraint of a closed-chain machine's loops: which closure equations are redundant.

A loop closed by a 3-D ``connect`` in a planar mechanism has three equations where the mechanism's joints
can meet only two: the out-of-plane one is redundant (Grübler–Kutzbach: the loops impose fewer independent
constraints than they have equations). On the real machine an error along a redundant direction (a hinge
axis tilted out of the plane, a link raised along its axis) is taken up by the clearance or the elastic
strain of the loop: the joints still move in the plane, and the links carry the tilt. A rigid model cannot
meet such an error at all, and the closure solver's compromise between the inconsistent equations (a least-
squares fit weighted by MuJoCo quantities, not by stiffness) lets it move the task point in the plane: left
free in identification, the tilts become knobs with no physical meaning that a fit drives far beyond their
prior to absorb whatever else the model misses (a planar five-bar fitted out-of-plane tilts of 2–6 deg
against a 0.1 deg prior and compensated worse than uncompensated).

The twin therefore closes its loops only along their independent directions when machine.toml gives no
``[closures]`` compliance (how many: :func:`redundant_directions` at ``home``; which, at each configuration:
the closure Jacobian's smallest singular directions there; the residual is projected off them, the real
joints' play takes that part): an error that only strains a loop moves nothing the
tracker sees (identification lists it as having no effect), one that also tilts a link moves the nests
as it does on the machine. With ``[closures]`` stiffness the strain is modelled instead, by the weights.
:func:`loop_redundancy` reports the count, the directions in words, and each error's *strain*: the share of
the closure residual it creates (joints held at home) that lies along the redundant directions.

Units: closure residuals in m at the model's scale, errors in mm / deg.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Relative singular value of the closure Jacobian (passive joints) below which a direction is redundant.
RANK_TOL = 1e-9
#: Share of an error's closure residual along the redundant directions above which it is a strain error.
STRAIN_TOL = 1e-3
#: Least strain (mm, for an error of its prior size) that counts: below it the residual is rounding.
STRAIN_MIN_MM = 1e-6
#: Step of the finite difference of the closure residual by an error, in units of its prior size.
_STEP = 1e-3


@dataclass
class LoopRedundancy:
    """Redundant closure equations of a machine at home and the errors that only strain them.

    n_equations : closure equations (3 per connect, 6 per weld).
    rank : independent ones (rank of the closure Jacobian with the motors held).
    directions : (n_equations - rank, n_equations) unit rows: the redundant combinations of equations.
    described : each redundant direction in words (the closure and axis it mostly lies along).
    strain : error key -> share of its closure residual along the redundant directions (0..1).
    strain_errors : the keys whose share exceeds :data:`STRAIN_TOL` (they strain a loop; with the loops
        closed along their independent directions only, what they do besides is what the twin shows).
    """

    n_equations: int
    rank: int
    directions: np.ndarray
    described: list[str]
    strain: dict[str, float] = field(default_factory=dict)
    strain_errors: list[str] = field(default_factory=list)

    @property
    def redundant(self) -> int:
        """Number of redundant closure equations."""
        return self.n_equations - self.rank


def redundant_directions(C: np.ndarray) -> np.ndarray:
    """The redundant directions (n_eq - rank, n_eq) of the closure Jacobian ``C`` (n_eq, n_passive; motors
    held): unit rows spanning the equation combinations no joint motion changes (SVD, relative threshold
    :data:`RANK_TOL`)."""
    U, sv, _ = np.linalg.svd(C, full_matrices=True)
    rank = int(np.sum(sv > RANK_TOL * max(float(sv.max(initial=0.0)), 1e-300)))
    return U[:, rank:].T


def _equation_names(twin) -> list[str]:
    names = []
    for c in twin.closures:
        names += [f"{c.name} {a}" for a in "xyz"]
    for c in twin.closures:
        if c.weld:
            names += [f"{c.name} r{a}" for a in "xyz"]
    return names


def loop_summary(twin) -> dict:
    """``{"closure_equations", "independent", "redundant"}``: the twin's closure equations, how many of
    them its joints can meet at home, and each redundant direction in words (e.g. ``"tip z (100% of it)"``)."""
    D = twin.redundant_directions
    names = _equation_names(twin)
    return {"closure_equations": int(twin.n_equations), "independent": int(twin.n_equations - len(D)),
            "redundant": [f"{names[int(np.argmax(np.abs(d)))]} ({np.max(np.abs(d)):.0%} of it)" for d in D]}


def _closure_residual(twin, q: np.ndarray) -> np.ndarray:
    """Unweighted, unprojected closure residual (n_eq,) m at ``q`` on the twin's current model."""
    twin._kin(q, jac=False)
    d = twin.data
    sp = d.site_xpos[twin.points][None]
    sm = d.site_xmat[twin.points].reshape(1, -1, 3, 3)
    return twin._gaps(sp, sm)[0]


def loop_redundancy(twin) -> LoopRedundancy:
    """The redundant closure equations of ``twin`` (a :class:`~pmcal.twin.closed_chain.ClosedChainTwin`) at
    its home configuration, and each geometric error's strain along them (module docstring). The twin's
    errors are left nominal."""
    twin.set_params(None)
    q = twin.solve(twin.home_commands[None])[0]
    if not np.isfinite(q).all():
        q = twin.home_qpos.copy()
    D = twin.redundant_directions
    described = loop_summary(twin)["redundant"]
    out = LoopRedundancy(n_equations=twin.n_equations, rank=twin.n_equations - len(D), directions=D,
                         described=described)
    if not len(D):
        return out
    r0 = _closure_residual(twin, q)
    keys = [k for k in twin.error_keys if not k.endswith(".dzero")]
    try:
        for k, s in zip(keys, twin.prior_std(keys)):
            twin.set_params({k: _STEP * s})
            dr = _closure_residual(twin, q) - r0
            along = float(np.linalg.norm(D @ dr))
            strained = along * 1e3 / _STEP > STRAIN_MIN_MM          # mm of strain for an error of its prior size
            out.strain[k] = along / float(np.linalg.norm(dr)) if strained else 0.0
    finally:
        twin.set_params(None)
    out.strain_errors = [k for k, v in out.strain.items() if v > STRAIN_TOL]
    return out
