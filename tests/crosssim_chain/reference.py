"""The reference calibration in this simulator's own parameters: a plain least-squares fit of
:class:`~tests.crosssim_chain.machine.SimMachine`'s errors to a campaign's nests, and the compensation with it.

Nothing of pmcal: the machine, its error parameterisation and its loop solver are :mod:`.machine`'s.

**Fit.** ``scipy.optimize.least_squares`` (trust-region reflective) of the nest residuals (mm) over every error
key of the simulator, from zero errors, no prior, the parameters scaled by their prior sizes (``[errors]``). The
parameterisation is redundant (about half of its directions move no nest at all) and many of its remaining
directions move the nests by far less than the tracker noise: a fit of those is set by the noise alone (in the
delta, singular values of 1e-9 of the largest, millimetres of task error). So the fit runs in the row space that
the data determine: the directions of the SVD of the scaled nest Jacobian at the nominal machine whose singular
value (the nests' displacement norm, mm, for a move of one prior size) is at least the tracker's sigma (their
noise-fitted part then below one prior size); the others stay at their zero start (truncated-SVD least squares:
the minimum-norm solution, what the data cannot tell apart left at zero).

**Cost made affordable, without changing what is computed.**

- Closures warm-started: each evaluation closes the loops with the simulator's own ``_close`` from the
  configurations of the previous evaluation (the motors set to the new commands/zeros), not from ``home`` by
  sub-steps. A warm closure that fails falls back to the simulator's full :meth:`SimMachine.solve`.
- The Jacobian by the implicit-function theorem instead of one closure solve per parameter and pose: at each
  pose's closed configuration q, the partial derivatives at fixed q of the nests F and the loop gaps G with
  respect to a parameter (central differences of the model recompiled with that parameter moved, the
  simulator's own ``_compile``; no closure solve) and with respect to the joints (central differences of q);
  then ``dF/dp = F_p - F_free pinv(G_free) G_p`` (the free joints follow the closure). A motor's zero is a
  motor-joint move. Exact where the loops close; where a loop is over-constrained (its gap left to play: the
  five-bar, the delta, the ToddlerBot neck) the closure is a least-squares solution and this derivative misses
  the gap's curvature term (0.1 % on the five-bar's tilts, 20 % on the neck's motor columns): there the
  optimiser runs on it and the converged point gets one Gauss-Newton step with the exact Jacobian (central
  differences through the closure, warm-started), kept if it lowers the cost (``polish_cost_change``).

**Compensation.** Per target, ``least_squares`` of the simulator's task (with the fitted errors) minus the
target over the motor commands, from the controller's nominal IK commands; the commands are then driven on the
true simulator by the caller.

Units: mm and deg at the interface (as :mod:`.machine`).
"""

from __future__ import annotations

import copy

import mujoco
import numpy as np
from scipy.optimize import least_squares

from .machine import SimMachine

H_PARAM = 1e-3          # mm / deg: central-difference step of an error parameter
H_JOINT = 1e-7          # rad / m: central-difference step of a joint


def variant(sim: SimMachine, errors: dict[str, float]) -> SimMachine:
    """``sim`` with errors ``errors``: the model recompiled, home and the rest shared (no closure solved)."""
    v = copy.copy(sim)
    v.errors = dict(errors)
    v.model = v._compile()
    v.data = mujoco.MjData(v.model)
    return v


def close_from(sim: SimMachine, q_start: np.ndarray, commands: np.ndarray) -> np.ndarray:
    """Configurations (N, nq) at ``commands`` (N, M), each closed from ``q_start[i]`` with the motors moved
    there; the simulator's full solve (from home) where that fails."""
    commands = np.atleast_2d(commands)
    out = np.empty((len(commands), sim.model.nq))
    for i, c in enumerate(commands):
        q = np.array(q_start[i], float)
        ok = np.isfinite(q).all()
        if ok:
            q[sim.motor_q] = sim._joint_of(c)
            q = sim._close(q)
            ok = np.isfinite(q).all()
        out[i] = q if ok else sim.solve(c[None])[0]
    return out


def _outputs(sim: SimMachine, q: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
    """(gaps, outputs) at ``q``: outputs the nests (K*3,) mm or the task (C,)."""
    g = sim._gaps(q)                                           # runs the kinematics
    if what == "nests":
        return g, sim.data.site_xpos[sim.target_ids].ravel() * 1000.0
    return g, sim.task_here()


def _wrap(d: np.ndarray, sim: SimMachine, what: str) -> np.ndarray:
    if what == "task":
        ang = np.array([c.endswith("_deg") for c in sim.coordinates])
        d[..., ang] = (d[..., ang] + 180.0) % 360.0 - 180.0
    return d


def joint_derivatives(sim: SimMachine, q: np.ndarray, what: str):
    """At the closed configuration ``q``: (F_free, pinv(G_free), D_motor): the outputs' partials on the free
    joints, the closure's pseudo-inverse on them, and the outputs' total derivative (the loops closed) with
    respect to each motor joint (rad or m)."""
    m = sim.model
    G, F = [], []
    for k in range(m.nv):
        cols = []
        for s in (1.0, -1.0):
            dv = np.zeros(m.nv)
            dv[k] = s * H_JOINT
            qq = q.copy()
            mujoco.mj_integratePos(m, qq, dv, 1.0)
            cols.append(_outputs(sim, qq, what))
        G.append((cols[0][0] - cols[1][0]) / (2 * H_JOINT))
        F.append(_wrap(cols[0][1] - cols[1][1], sim, what) / (2 * H_JOINT))
    G, F = np.array(G).T, np.array(F).T
    motor_dof = [int(m.jnt_dofadr[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, j)]) for j in sim.motors]
    free = sim.free_dofs
    Gp = np.linalg.pinv(G[:, free]) if len(free) else np.zeros((0, len(G)))
    D_motor = F[:, motor_dof] - F[:, free] @ (Gp @ G[:, motor_dof])
    return F[:, free], Gp, D_motor


def motor_units(sim: SimMachine) -> np.ndarray:
    """Joint move (rad or m) per command unit (deg or mm), per motor."""
    return np.where(sim.hinge, np.deg2rad(1.0), 1e-3)


def over_constrained(sim: SimMachine, qs: np.ndarray) -> bool:
    """Whether a loop is left open (an over-constrained loop's gap taken up by play, above 1e-6 mm) at one of
    the closed configurations ``qs``: there the closure is a least-squares solution whose derivative the
    implicit-function step (which assumes closed loops) does not give exactly."""
    return any(np.max(np.abs(sim._gaps(q))) > 1e-6 for q in qs)


def jacobian(sim: SimMachine, qs: np.ndarray, keys: list[str], what: str = "nests",
             commands: np.ndarray | None = None) -> np.ndarray:
    """d outputs / d errors (N*n_out, len(keys)) at the closed configurations ``qs`` (N, nq) of ``sim``
    (per mm / deg), the loops closed: by the implicit-function theorem (see the module's doc), or, where a loop
    is over-constrained (:func:`over_constrained`) and ``commands`` (N, M) are given, by central differences
    through the simulator's closure warm-started at ``qs``."""
    if commands is not None and over_constrained(sim, qs):
        return _jacobian_closing(sim, qs, keys, what, commands)
    per_pose = [joint_derivatives(sim, q, what) for q in qs]
    n_out = per_pose[0][0].shape[0]
    J = np.zeros((len(qs), n_out, len(keys)))
    units = motor_units(sim)
    for c, key in enumerate(keys):
        frame, _, comp = key.rpartition("/")
        if comp == "zero":
            j = sim.motors.index(frame)
            for i, (_, _, D) in enumerate(per_pose):
                J[i, :, c] = D[:, j] * units[j]
            continue
        lo, hi = (variant(sim, {**sim.errors, key: sim.errors.get(key, 0.0) + s * H_PARAM}) for s in (-1.0, 1.0))
        for i, (q, (Ff, Gp, _)) in enumerate(zip(qs, per_pose)):
            gh, fh = _outputs(hi, q, what)
            gl, fl = _outputs(lo, q, what)
            Gk = (gh - gl) / (2 * H_PARAM)
            Fk = _wrap(fh - fl, sim, what) / (2 * H_PARAM)
            J[i, :, c] = Fk - Ff @ (Gp @ Gk)
    return J.reshape(-1, len(keys))


def _jacobian_closing(sim, qs, keys, what, commands) -> np.ndarray:
    cols = []
    for key in keys:
        out = []
        for s in (1.0, -1.0):
            v = variant(sim, {**sim.errors, key: sim.errors.get(key, 0.0) + s * H_PARAM})
            q = close_from(v, qs, commands)
            out.append(np.array([_outputs(v, qi, what)[1] for qi in q]))
        cols.append(_wrap(out[0] - out[1], sim, what).ravel() / (2 * H_PARAM))
    return np.array(cols).T


def command_jacobian(sim: SimMachine, q: np.ndarray, c: np.ndarray) -> np.ndarray:
    """d task / d commands (C, M) at the closed configuration ``q`` at commands ``c`` (as :func:`jacobian`)."""
    if not over_constrained(sim, q[None]):
        return joint_derivatives(sim, q, "task")[2] * motor_units(sim)
    cols = []
    for j in range(len(c)):
        out = []
        for s in (1.0, -1.0):
            cc = np.array(c, float)
            cc[j] += s * H_PARAM
            qq = close_from(sim, q[None], cc[None])[0]
            out.append(_outputs(sim, qq, "task")[1])
        cols.append(_wrap(out[0] - out[1], sim, "task") / (2 * H_PARAM))
    return np.array(cols).T


def sizes(sim: SimMachine) -> np.ndarray:
    """Prior sizes (mm / deg) of the error keys, the fit's parameter scale."""
    return np.array(sim._size, float)


def fit(sim0: SimMachine, commands: np.ndarray, measured: np.ndarray, q_start: np.ndarray, sigma_mm: float,
        max_nfev: int = 20, prior: bool = False) -> dict:
    """Plain least squares of ``sim0``'s errors (from zero; ``sim0`` is the nominal simulator) to the nests
    ``measured`` (N, K, 3) mm at ``commands`` (N, M). ``q_start`` (N, nq): configurations near the solution
    to warm-start the closures (any assembled configurations of the same branch); ``sigma_mm`` the tracker's
noise (the row-space floor, see the module's doc). ``prior``: instead of the truncated row space, every
    error with the simulator's own prior (normal, the toml's sizes: the distribution its random errors are
    drawn from), the posterior mode (maximum a posteriori, the Bayes-optimal estimate in the linear regime):
    what the best any calibration can do on average, knowing the true error distribution. Returns {errors,
    rank, n_params, nfev, njev, cost, rms_residual_mm, q}."""
    keys, s = sim0.error_keys, sizes(sim0)
    measured = np.asarray(measured, float).reshape(len(commands), -1)
    state = {"q": np.asarray(q_start, float), "cache": {}}

    def at(x: np.ndarray):
        key = x.tobytes()
        if key not in state["cache"]:
            sim = variant(sim0, dict(zip(keys, s * x)))
            q = close_from(sim, state["q"], commands)
            state["q"] = q
            state["cache"] = {key: (sim, q)}                   # the last point only
        return state["cache"][key]

    def nests(sim, q):
        return np.array([_outputs(sim, qi, "nests")[1] for qi in q])

    sim, q = at(np.zeros(len(keys)))
    J0 = jacobian(sim, q, keys) * s
    _, sv, Vt = np.linalg.svd(J0, full_matrices=False)
    rank = int(np.sum(sv >= sigma_mm))
    V = np.eye(len(keys)) if prior else Vt[:rank].T            # the row space: what the nests see
    weight = sigma_mm if prior else 0.0                        # prior rows: x (prior sizes) against the noise

    def residual(z):
        sim, q = at(V @ z)
        return np.concatenate([(nests(sim, q) - measured).ravel(), weight * z])

    def jac(z):
        sim, q = at(V @ z)
        return np.vstack([(jacobian(sim, q, keys) * s) @ V, weight * np.eye(V.shape[1])])

    sol = least_squares(residual, np.zeros(V.shape[1]), jac=jac, method="trf", x_scale=1.0, ftol=1e-10, xtol=1e-10,
                        gtol=1e-10, max_nfev=max_nfev)
    z, r = sol.x, residual(sol.x)
    polish = None
    if over_constrained(*at(V @ z)):
        # an over-constrained loop: the implicit-function Jacobian is approximate there; one Gauss-Newton step
        # with the exact one (central differences through the closure) from the converged point, kept if it
        # lowers the cost
        sim, q = at(V @ z)
        Jb = np.vstack([(jacobian(sim, q, keys, commands=commands) * s) @ V, weight * np.eye(V.shape[1])])
        z2 = z - np.linalg.lstsq(Jb, r, rcond=None)[0]
        r2 = residual(z2)
        polish = float(0.5 * (r2 @ r2) - 0.5 * (r @ r))
        if polish < 0:
            z, r = z2, r2
    x = V @ z
    sim, q = at(x)
    r = r[:measured.size]                                      # the nests' residuals, without the prior rows
    return {"errors": dict(zip(keys, s * x)), "rank": rank, "n_params": len(keys), "nfev": int(sol.nfev),
            "njev": int(sol.njev), "cost": float(0.5 * r @ r), "rms_residual_mm": float(np.sqrt(np.mean(r ** 2))),
            "status": int(sol.status), "polish_cost_change": polish, "singular_values": sv, "q": q}


def inverse(sim: SimMachine, targets: np.ndarray, start: np.ndarray, q_start: np.ndarray,
            iterations: int = 30, tol: float = 1e-9) -> np.ndarray:
    """Commands (N, M) that put ``sim``'s task at ``targets`` (N, C): Gauss-Newton least squares on the
    commands per target from ``start`` (minimum-norm steps where the motors are redundant, halved while they do
    not reduce the residual; until every |residual| < ``tol`` mm / deg); ``q_start`` near-by configurations
    to warm-start the closures. A target not reached stays at the best commands found."""
    out = np.array(start, float, copy=True)
    for i, target in enumerate(np.atleast_2d(targets)):
        c = out[i]
        q = close_from(sim, np.asarray(q_start[i], float)[None], c[None])[0]
        r = _wrap(_outputs(sim, q, "task")[1] - target, sim, "task")
        for _ in range(iterations):
            if np.max(np.abs(r)) < tol:
                break
            step = np.linalg.lstsq(command_jacobian(sim, q, c), -r, rcond=None)[0]
            for _ in range(10):
                c2 = c + step
                q2 = close_from(sim, q[None], c2[None])[0]
                r2 = _wrap(_outputs(sim, q2, "task")[1] - target, sim, "task")
                if np.isfinite(r2).all() and r2 @ r2 < r @ r:
                    break
                step = step / 2
            else:
                break
            c, q, r = c2, q2, r2
        out[i] = c
    return out
