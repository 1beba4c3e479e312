"""``pmcal identify | compensate | evaluate | demo`` for the over-constrained PM (seed 000, IV-VI).

File formats: spec INTERFACES.md (mm and degrees). Numerics live in :mod:`calib`; this module reads
and validates input, runs the calibration, writes outputs atomically and builds the demo report.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from pmcal.calib.ocpm import compensation as comp
from pmcal.calib.ocpm import paper_model as pm
from pmcal.mechanism.ocpm.config import Geometry, default_geometry
from pmcal.mechanism.ocpm.kinematics import limb_ik, real_ik_commands
from pmcal.mechanism.ocpm.params import ErrorSet
from pmcal.mechanism.rotations import pointing_error, tilt_torsion, tilt_torsion_angles
from pmcal.calib.solvers import METHODS
from pmcal import progress
from pmcal.errors import InputError
from pmcal.fileio import write_json
from pmcal.io_ocpm import MECHANISM, read_measurements, read_params, read_targets, write_params, write_setpoints

DEFAULT_METHOD = "hga"
DEFAULT_GRID = (73, 31)          # 5 deg in phi over 0..360, 2 deg in theta over 0..60


# ====================================================================== identify
def check_method(method: str | None) -> str:
    method = method or DEFAULT_METHOD
    if method not in METHODS:
        raise InputError(f"unknown method '{method}' (known: {', '.join(METHODS)})", field="--method")
    return method


def check_sigma(sigma: float | None, geom: Geometry) -> float:
    sigma = geom.sigma_mm if sigma is None else float(sigma)
    if not (np.isfinite(sigma) and sigma > 0):
        raise InputError(f"tracker noise must be a positive number of mm, got {sigma}", field="--sigma")
    return sigma


MODELS = ("full", "paper")
DEFAULT_MODEL = "full"      # the whole closed chain (docs/fullchain.md); "paper" is the seed's per-limb model


def check_model(model: str | None) -> str:
    model = model or DEFAULT_MODEL
    if model not in MODELS:
        raise InputError(f"unknown model '{model}' (known: {', '.join(MODELS)})", field="--model")
    return model


def check_reachable(meas, path: str, geom: Geometry) -> None:
    """Every measured pose must be within reach of the actuated limbs of the nominal machine."""
    r, R, _ = meas.poses(geom)
    ik = limb_ik(r, R, None, geom, (1, 2))
    bad = np.argwhere(~np.isfinite(ik.beta) & np.isfinite(r).all(axis=1)[:, None])   # NaN r: blocked target
    if bad.size:
        i, j = (int(v) for v in bad[0])
        raise InputError(f"the measured platform pose is out of reach of limb {j + 1} (|K/rho| = "
                         f"{abs(ik.reach[i, j]):.3g} > 1): not a pose of this machine", file=path, row=i + 1,
                         field="t1_x")


def calibrate_file(meas, method: str, sigma: float, seed: int | None, geom: Geometry, **options):
    """Identify both actuated limbs (progress bar per limb) and fit the position map."""
    with progress.progress(total=2, desc=f"identify ({method})", unit="limb") as bar:
        cal = pm.calibrate(meas, method, (1, 2), seed=seed, sigma_mm=sigma, geom=geom,
                           on_limb_done=lambda j, res: bar.update(1), **options)
    pmap = comp.fit_position_map(cal.model.r, cal.model.R, geom)
    return cal, pmap


def params_document(cal, pmap: comp.PositionMap, method: str, sigma: float, source: str) -> dict:
    """Everything ``write_params`` records besides the parameters (INTERFACES.md, extended)."""
    motor = np.rad2deg(cal.model.motor_residual(cal.x))
    cond = {f"L{j}": a.condition_number for j, a in cal.identifiability.items()}
    weak = [k for a in cal.identifiability.values() for k in a.weak]
    chi = np.concatenate([r.residuals for r in cal.results.values()])
    return {
        "model": "paper", "method": method, "source": source,
        "uncertainty": cal.uncertainty(),
        "identifiability": {
            "condition_number": max(cond.values()), "condition_number_per_limb": cond,
            "unidentifiable": cal.unidentifiable,
            "explanations": {k: pm.explain(k) for k in cal.unidentifiable},
            "weak": weak,
            "note": "condition number of the column-normalised whitened Jacobian at the solution; "
                    "unidentifiable: no first-order effect on the motor angles (held at 0); weak: "
                    "Cramer-Rao std larger than the search box half-width",
        },
        "fit": {"n_poses": int(len(motor)), "noise_sigma_mm": sigma,
                "residual_rms_sigma": float(np.sqrt(np.mean(chi**2))),
                "motor_residual_rms_deg": {f"L{j}": float(np.sqrt(np.mean(motor[:, i] ** 2)))
                                           for i, j in enumerate((1, 2))}},
        "position_map": pmap.to_dict(),
        "solver": {f"L{j}": {"n_eval": r.n_eval, "n_iter": r.n_iter, "wall_time_s": r.wall_time,
                             "success": r.success, "message": r.message} for j, r in cal.results.items()},
    }


#: Fewest poses the whole-chain fit accepts: ~40 effective parameters, 6 pose coordinates a pose.
MIN_POSES_FULL = 12


def identify(args) -> int:
    geom = default_geometry()
    model = check_model(args.model)
    if model == "full":
        return identify_full_chain(args, geom)
    if (getattr(args, "frame", None) or "base") != "base":
        raise InputError("--frame tracker needs the whole-chain model (--model full)", field="--frame")
    method = check_method(args.method)
    sigma = check_sigma(args.sigma, geom)
    meas = read_measurements(args.measurements, geom)
    n_free = len(pm.SEED_LIMB_FIELDS)
    if len(meas) <= n_free:
        raise InputError(f"{len(meas)} poses cannot determine {n_free} parameters a limb: measure at least "
                         f"{n_free + 1} (the seed uses 24)", file=args.measurements, field="pose_id")
    check_reachable(meas, args.measurements, geom)
    cal, pmap = calibrate_file(meas, method, sigma, args.seed, geom)
    doc = params_document(cal, pmap, method, sigma, str(args.measurements))
    write_params(args.output, cal.params(), **doc)
    progress.status(f"identified {len(cal.params())} parameters ({method}); residual "
                    f"{doc['fit']['residual_rms_sigma']:.3g} sigma; written {args.output}")
    return 0


def identify_full_chain(args, geom: Geometry) -> int:
    """``pmcal identify --model full`` (the default): the whole closed chain, all limbs and SS."""
    from pmcal.apps.ocpm_full import result_document
    from pmcal.apps.ocpm_tracker import check_nest_tolerance, identify_result, parse_frame, tracker_document
    from pmcal.twin.forward import FullChainModel

    frame, reg0 = parse_frame(getattr(args, "frame", None))
    nest_std = check_nest_tolerance(getattr(args, "nest_tolerance", None))
    if args.method is not None:
        raise InputError("--method chooses the solver of --model paper; the whole-chain model is fitted by "
                         "MAP least squares (give --model paper to use the seed's methods)", field="--method")
    sigma = check_sigma(args.sigma, geom)
    meas = read_measurements(args.measurements, geom, frame=frame)
    if len(meas) < MIN_POSES_FULL:
        raise InputError(f"{len(meas)} poses are too few for the whole-chain model: measure at least "
                         f"{MIN_POSES_FULL} (24-48 recommended, docs/fullchain.md)", file=args.measurements,
                         field="pose_id")
    if frame == "base":
        check_reachable(meas, args.measurements, geom)
    progress.status(f"identifying the whole closed chain from {len(meas)} poses ({frame} frame)")
    res = identify_result(meas, FullChainModel(geom), sigma, frame, reg0, nest_std,
                          robust=True if getattr(args, "robust", False) else None, source=str(args.measurements))
    params, doc = result_document(res, meas, sigma, str(args.measurements), True)
    doc.update(tracker_document(res, meas, geom))
    for r in doc.get("rejected", []):
        progress.status(f"rejected outlier: row {r['row']} ({r['pose_id']}) target t{r['target']}, "
                        f"residual {r['residual_mm']:.3g} mm")
    write_params(args.output, params, **doc)
    progress.status(f"identified {len(params)} parameters (whole chain); chi2/dof "
                    f"{doc['fit']['chi2_per_dof']:.3g}; written {args.output}")
    return 0


# ====================================================================== compensate
def load_compensation(path: str, geom: Geometry) -> tuple[ErrorSet, comp.PositionMap | None, dict]:
    """Errors and position map from a parameters file (InputError naming file and field)."""
    params, doc = read_params(path, geom)
    model = doc.get("model", DEFAULT_MODEL)     # any parameter set: the whole chain is the better physics
    if model not in MODELS:
        raise InputError(f"unknown model '{model}' (known: {', '.join(MODELS)})", file=path, field="model")
    errors = ErrorSet.from_dict(params, geom.n_limbs, geom.actuated)
    if model == "full":
        from pmcal.apps.ocpm_full import FullCompensation

        ratio = doc.get("stiffness_ratio")
        if ratio is not None and not (isinstance(ratio, (int, float)) and np.isfinite(ratio) and ratio > 0):
            raise InputError(f"stiffness ratio {ratio!r} is not a positive number", file=path,
                             field="stiffness_ratio")
        return errors, FullCompensation(params, ratio, geom), doc
    pmap = None
    if doc.get("position_map") is not None:
        try:
            pmap = comp.PositionMap.from_dict(doc["position_map"])
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"invalid position map ({exc})", file=path, field="position_map") from None
    return errors, pmap, doc


def compensated_commands(phi_deg, theta_deg, errors, pmap, geom: Geometry, path: str | None = None,
                         field: str = "theta_deg") -> np.ndarray:
    """Motor commands (N, 2) deg; InputError naming the first unreachable / out-of-limits row.

    ``pmap`` is the paper model's position map (or None: eq. 7), or a whole-chain ``FullCompensation``.
    """
    if hasattr(pmap, "commands_deg"):
        m = pmap.commands_deg(phi_deg, theta_deg)
    else:
        m = np.rad2deg(comp.setpoints(np.deg2rad(phi_deg), np.deg2rad(theta_deg), errors, geom, pmap))
    lo, hi = _deg(geom.motor_min), _deg(geom.motor_max)
    bad = np.flatnonzero(~np.all(np.isfinite(m) & (m >= lo) & (m <= hi), axis=1))
    if bad.size:
        i = int(bad[0])
        what = "is out of reach of the calibrated machine" if not np.all(np.isfinite(m[i])) else \
            f"needs motor commands {m[i].round(3)} deg outside the limits [{lo:g}, {hi:g}] deg"
        raise InputError(f"orientation (phi {phi_deg[i]:g}, theta {theta_deg[i]:g}) deg {what}",
                         file=path, row=i + 1, field=field)
    return m


def parse_grid(text: str | None) -> tuple[int, int]:
    if text is None:
        return DEFAULT_GRID
    try:
        n_phi, n_theta = (int(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"expected NPHI,NTHETA (two integers), got '{text}'", field="--grid") from None
    if not (2 <= n_phi <= 100 and 2 <= n_theta <= 100):
        raise InputError(f"grid {n_phi}x{n_theta} outside 2x2..100x100 (PLC array size)", field="--grid")
    return n_phi, n_theta


def _deg(rad: float) -> float:
    """Degrees of a configured angle, rounded to 1e-9 deg (60 stays 60, not 59.99999999999999)."""
    return round(float(np.rad2deg(rad)), 9)


def build_table(errors, pmap, geom: Geometry, grid: tuple[int, int], version: int):
    """The 2-D compensation table over phi 0..360 and theta 0..theta_max (deg), validated."""
    from pmcal.bridge.comptable import CompTable

    def fill(phi_deg, theta_deg):
        return compensated_commands(phi_deg, theta_deg, errors, pmap, geom, field="grid")

    table = CompTable.from_setpoints(fill, machine=MECHANISM, version=version, n_phi=grid[0], n_theta=grid[1],
                                     theta_range_deg=(0.0, _deg(geom.theta_max)),
                                     motor_limits_deg=(_deg(geom.motor_min), _deg(geom.motor_max)))
    return table.validate()


def compensate(args) -> int:
    from pmcal.twin.campaign import THETA_LIMIT_DEG

    geom = default_geometry()
    if not args.targets and not args.table:
        raise InputError("nothing to do: give --targets TARGETS.csv -o SETPOINTS.csv and/or --table TABLE.json",
                         field="--targets")
    if args.targets and not args.output:
        raise InputError("--targets needs -o SETPOINTS.csv", field="-o")
    if args.output and not args.targets:
        raise InputError("-o SETPOINTS.csv needs --targets TARGETS.csv", field="--targets")
    errors, pmap, _ = load_compensation(args.params, geom)
    grid = parse_grid(args.grid)
    version = getattr(args, "table_version", None)
    version = int(time.time()) if version is None else int(version)
    if not 1 <= version <= 2**32 - 1:
        raise InputError(f"table version {version} outside 1..4294967295", field="--table-version")
    work = []                                          # compute everything before writing anything
    if args.targets:
        phi, theta = read_targets(args.targets, theta_max_deg=THETA_LIMIT_DEG)
        m = compensated_commands(phi, theta, errors, pmap, geom, args.targets)
        note = f"pmcal compensate: {args.params}, " + (
            "whole closed chain, Newton on the forward model" if hasattr(pmap, "commands_deg") else
            "exact real IK, position: " + ("fitted map" if pmap is not None else "nominal (seed eq. 7)"))
        work.append(lambda: write_setpoints(args.output, phi, theta, m, comments=[note]))
    if args.table:
        table = build_table(errors, pmap, geom, grid, version)
        work.append(lambda: table.save(args.table))
    for w in work:
        w()
    return 0


# ====================================================================== evaluate
def evaluate_params(meas, errors: ErrorSet, pmap, geom: Geometry) -> dict:
    """Where the calibrated model says the commands go vs where the platform was measured."""
    r, R, _ = meas.poses(geom)
    if hasattr(pmap, "commands_deg"):                  # whole chain: forward model, then its inverse
        phi, theta = pmap.orientation(meas.m_cmd_deg)
        phi_m, theta_m = tilt_torsion_angles(R)
        motor = pmap.commands_deg(np.rad2deg(phi_m), np.rad2deg(theta_m)) - meas.m_cmd_deg
    else:
        phi, theta = comp.predict_orientation(np.deg2rad(meas.m_cmd_deg), errors, geom, pmap)
        motor = np.rad2deg(real_ik_commands(r, R, errors, geom)) - meas.m_cmd_deg
    err = np.rad2deg(pointing_error(tilt_torsion(phi, theta), R))
    stats = lambda a: {"rms": float(np.sqrt(np.nanmean(a**2))), "mean": float(np.nanmean(np.abs(a))),  # noqa: E731
                       "max": float(np.nanmax(np.abs(a)))}
    return {"n_poses": len(meas), "pointing_error_deg": stats(err),
            "motor_residual_deg": {"m1": stats(motor[:, 0]), "m2": stats(motor[:, 1])},
            "per_pose": [{"pose_id": pid, "pointing_error_deg": float(e), "m1_residual_deg": float(a),
                          "m2_residual_deg": float(b)} for pid, e, (a, b) in zip(meas.pose_id, err, motor)]}


def evaluate(args) -> int:
    geom = default_geometry()
    errors, pmap, doc = load_compensation(args.params, geom)
    meas = read_measurements(args.measurements, geom)
    out = evaluate_params(meas, errors, pmap, geom)
    out = {"mechanism": MECHANISM, "params_file": str(args.params), "measurements": str(args.measurements),
           "model": doc.get("model", DEFAULT_MODEL),
           "position": "whole closed chain" if hasattr(pmap, "commands_deg") else
           ("fitted map" if pmap is not None else "nominal (eq. 7)"),
           "unit": "deg", **out}
    pe = out["pointing_error_deg"]
    print(f"pointing error over {out['n_poses']} poses: rms {pe['rms']:.4f} deg, max {pe['max']:.4f} deg")
    if args.json:
        write_json(args.json, out)
    return 0


# ====================================================================== demo: studies
def reached(twin, phi_deg, theta_deg, m_deg) -> dict[str, np.ndarray]:
    """Drive the twin to commands (N, 2) deg and compare with the target orientations (deg).

    Returns pointing error (angle between platform normals), tilt and azimuth deviations, deg.
    """
    st = twin.reach(m_deg)
    phi, theta = tilt_torsion_angles(st.R)
    target = tilt_torsion(np.deg2rad(phi_deg), np.deg2rad(theta_deg))
    dphi = np.rad2deg(np.angle(np.exp(1j * (phi - np.deg2rad(phi_deg)))))
    return {"pointing": np.rad2deg(pointing_error(st.R, target)), "dtheta": np.rad2deg(theta) - theta_deg,
            "dphi": dphi}


def held_out(twin, errors: ErrorSet, pmap, phi_deg, theta_deg, geom: Geometry) -> dict[str, np.ndarray]:
    """Pointing errors on test poses after compensation with ``errors`` and ``pmap``."""
    m = np.rad2deg(comp.setpoints(np.deg2rad(phi_deg), np.deg2rad(theta_deg), errors, geom, pmap))
    return reached(twin, phi_deg, theta_deg, m)


def parameter_errors(cal, truth: dict[str, float]) -> dict[str, float]:
    """Identified minus predefined, interface units (mm, deg), identifiable parameters only."""
    got = cal.params()
    return {k: got[k] - truth.get(k, 0.0) for k in cal.names if k in got}


def _timed_calibration(meas, method: str, seed: int):
    """(calibration, wall time) of one method on both limbs (a worker-process entry point)."""
    t0 = time.perf_counter()
    cal = pm.calibrate(meas, method, seed=seed)
    return cal, time.perf_counter() - t0


class DemoStudy:
    """The demo's computations, one method per step; results kept for the report (mm, deg)."""

    N_CAL = 24
    N_TEST = 24
    N_REG = 96            # the seed's regularisation study uses 96 poses (section VI-A)
    METHODS_COMPARED: tuple[str, ...] = METHODS

    def __init__(self, seed: int):
        from pmcal.mechanism.ocpm.params import PAPER_TABLE2
        from pmcal.twin.machine import Twin

        self.seed, self.geom = seed, default_geometry()
        self.truth = dict(PAPER_TABLE2)
        self.twin = Twin(self.truth)
        self.theta_max = _deg(self.geom.theta_max)
        self.timings: dict[str, float] = {}
        self.methods: dict[str, dict] = {}

    def _timed(self, name: str, t0: float) -> None:
        self.timings[name] = time.perf_counter() - t0

    def campaign(self, n: int, seed: int, theta_max: float | None = None, plan=None):
        from pmcal.twin.campaign import plan_campaign, run_campaign
        from pmcal.twin.tracker import LaserTracker

        plan = plan or plan_campaign(n, theta_max or self.theta_max, seed)
        return run_campaign(self.twin, plan, LaserTracker(self.geom.sigma_mm, np.random.default_rng(seed)))

    # ------------------------------------------------------------------ steps
    def step_campaign(self, out: Path) -> None:
        from pmcal.twin.campaign import plan_campaign

        t0 = time.perf_counter()
        from pmcal.twin.campaign import plan_campaign as _plan

        self.meas_plan = _plan(self.N_CAL, self.theta_max, self.seed)
        self.meas = self.campaign(self.N_CAL, self.seed, plan=self.meas_plan)
        self.test = plan_campaign(self.N_TEST, self.theta_max, self.seed + 1000)
        r, R, _ = self.meas.poses(self.geom)
        st = self.twin.reach(self.meas.m_cmd_deg)
        self.closure = st.closure_residual                     # (N, 4) mm
        self._timed("campaign", t0)

    def step_identify(self, out: Path) -> None:
        t0 = time.perf_counter()
        self.cal, self.pmap = calibrate_file(self.meas, "hga", self.geom.sigma_mm, self.seed, self.geom)
        self._timed("identify", t0)
        doc = params_document(self.cal, self.pmap, "hga", self.geom.sigma_mm, "calibration_meas.csv")
        write_params(out / "params.json", self.cal.params(), **doc)
        self.params_doc = doc

    def step_compensate(self, out: Path) -> None:
        from pmcal.twin.campaign import nominal_commands

        t0 = time.perf_counter()
        ph, th = self.test.phi_deg, self.test.theta_deg
        e_hat, e_true = self.cal.errors(), ErrorSet.from_dict(self.truth)
        m_before = nominal_commands(ph, th, self.geom)
        m_after = compensated_commands(ph, th, e_hat, self.pmap, self.geom)
        write_setpoints(out / "test_setpoints.csv", ph, th, m_after,
                        comments=["pmcal demo: compensated commands of the 24 test poses"])
        lin = np.rad2deg(comp.setpoints_linear(np.deg2rad(ph), np.deg2rad(th), e_hat, self.geom))
        eq7 = np.rad2deg(comp.setpoints(np.deg2rad(ph), np.deg2rad(th), e_hat, self.geom))
        eq7_true = np.rad2deg(comp.setpoints(np.deg2rad(ph), np.deg2rad(th), e_true, self.geom))
        self.variants = {
            "before (nominal commands)": reached(self.twin, ph, th, m_before),
            "HGA + real IK + fitted position map (pmcal)": reached(self.twin, ph, th, m_after),
            "HGA + real IK + eq. 7 position (seed)": reached(self.twin, ph, th, eq7),
            "HGA + linearised eq. 15 (seed)": reached(self.twin, ph, th, lin),
            "true Table 2 errors + real IK + eq. 7": reached(self.twin, ph, th, eq7_true),
        }
        self.before = self.variants["before (nominal commands)"]
        self.after = self.variants["HGA + real IK + fitted position map (pmcal)"]
        self._timed("compensate", t0)

    def step_algorithms(self, out: Path) -> None:
        """Every method on the same data; the slow population methods run in two worker processes."""
        from concurrent.futures import ProcessPoolExecutor

        t0 = time.perf_counter()
        slow = [m for m in self.METHODS_COMPARED if m in ("ga", "pso", "sa")]
        with ProcessPoolExecutor(max_workers=2) as pool:
            futures = {m: pool.submit(_timed_calibration, self.meas, m, self.seed) for m in slow}
            runs = {m: _timed_calibration(self.meas, m, self.seed) for m in self.METHODS_COMPARED
                    if m not in slow and m != "hga"}
            runs.update({m: f.result() for m, f in futures.items()})
        runs["hga"] = (self.cal, self.cal.wall_time)
        for method in self.METHODS_COMPARED:
            cal, wall = runs[method]
            ho = held_out(self.twin, cal.errors(), self.pmap, self.test.phi_deg, self.test.theta_deg, self.geom)
            chi = np.concatenate([r.residuals for r in cal.results.values()])
            self.methods[method] = {"cal": cal, "wall": wall, "chi_rms": float(np.sqrt(np.mean(chi**2))),
                                    "n_eval": sum(r.n_eval for r in cal.results.values()),
                                    "dev": parameter_errors(cal, self.truth), "held_out": ho["pointing"]}
        self._timed("algorithms", t0)

    def step_regularisation(self, out: Path) -> None:
        from pmcal.calib.solvers import identify
        from pmcal.calib.solvers.linear import lcurve, lcurve_corner

        t0 = time.perf_counter()
        meas96 = self.campaign(self.N_REG, self.seed + 2000)
        lin = pm.linear_pose_model(meas96, sigma_mm=self.geom.sigma_mm, geom=self.geom)
        prob = lin.problem()
        A = lin.matrix() * prob.scale
        b = -prob.residuals(prob.x0)
        self.lcurve = lcurve(A, b) + (lcurve_corner(A, b),)
        self.reg_cond = float(np.linalg.cond(A / np.linalg.norm(A, axis=0)))
        r96, R96, _ = meas96.poses(self.geom)
        pmap96 = comp.fit_position_map(r96, R96, self.geom)
        self.regular = {}
        for method in ("tikhonov", "tsvd"):
            res = identify(prob, method, fix_unidentifiable=False)
            errors = pm.errors_from_vector(res.names, res.x)
            self.regular[f"{method} (linear pose model, {self.N_REG} poses)"] = {
                "res": res, "held_out": held_out(self.twin, errors, pmap96, self.test.phi_deg,
                                                 self.test.theta_deg, self.geom)}
        self.regular[f"hga (real IK model, {self.N_CAL} poses)"] = {"res": None, "held_out": self.after}
        self._timed("regularisation", t0)

    def step_identifiability(self, out: Path) -> None:
        self.design = self.cal.design
        self.ident = self.cal.identifiability

    def step_pose(self, out: Path) -> None:
        from pmcal.calib.pose_selection import condition_number, crlb_std, join_blocks, select_poses
        from pmcal.twin.campaign import CampaignPlan, plan_orientations

        t0 = time.perf_counter()
        rng = np.random.default_rng(self.seed + 3000)
        ph, th = plan_orientations(600, self.theta_max, rng)
        names = [k for k in pm.param_names() if k not in self.cal.unidentifiable]
        B = pm.design_blocks(np.deg2rad(ph), np.deg2rad(th), names, geom=self.geom)
        B_joint = join_blocks(B, comp.position_map_blocks(np.deg2rad(ph), np.deg2rad(th)))
        rand = [rng.choice(len(ph), self.N_CAL, replace=False) for _ in range(200)]
        self.pose_sel = {"names": names, "random (median of 200)": {
            "cond": float(np.median([condition_number(B, i) for i in rand])),
            "crlb": np.median([crlb_std(B, i) for i in rand], axis=0)}}
        for label, blocks in (("D-optimal (identification)", B), ("D-optimal (identification + position map)",
                                                                   B_joint)):
            sel = select_poses(blocks, self.N_CAL, "D")
            plan = CampaignPlan(phi_deg=ph[sel], theta_deg=th[sel], approach=np.ones((self.N_CAL, 2)),
                                time_s=np.arange(self.N_CAL) * 30.0)
            meas = self.campaign(self.N_CAL, self.seed + 4000, plan=plan)
            cal, pmap = calibrate_file(meas, "hga", self.geom.sigma_mm, self.seed, self.geom)
            self.pose_sel[label] = {
                "cond": condition_number(B, sel), "crlb": crlb_std(B, sel), "dev": parameter_errors(cal, self.truth),
                "held_out": held_out(self.twin, cal.errors(), pmap, self.test.phi_deg, self.test.theta_deg,
                                     self.geom)["pointing"]}
        self._timed("pose selection", t0)

    def step_fullchain(self, out: Path) -> None:
        """Seed method vs whole closed chain on the same data: Table 2 errors in limbs 1-2, and the same
        machine with 0.5 mm / 0.1 deg (1 sigma) errors added to the passive limbs and the SS limb."""
        from pmcal.mechanism.ocpm.params import random_errors
        from pmcal.apps.ocpm_full import FullCompensation, identify_document
        from pmcal.twin.campaign import nominal_commands, run_campaign
        from pmcal.twin.machine import Twin
        from pmcal.twin.tracker import LaserTracker

        t0 = time.perf_counter()
        ph, th = self.test.phi_deg, self.test.theta_deg
        extra = random_errors(np.random.default_rng(self.seed + 5000), 0.5, 0.1, limbs=(3, 4),
                              distribution="normal")
        cases = {"Table 2, limbs 1-2": (self.twin, self.meas, self.cal.errors(), self.pmap)}
        twin2 = Twin({**self.truth, **extra})
        meas2 = run_campaign(twin2, self.meas_plan, LaserTracker(self.geom.sigma_mm, np.random.default_rng(self.seed)))
        cal2, pmap2 = calibrate_file(meas2, "hga", self.geom.sigma_mm, self.seed, self.geom)
        cases["Table 2 + passive limbs and SS (0.5 mm / 0.1 deg)"] = (twin2, meas2, cal2.errors(), pmap2)
        self.fullchain = {}
        for name, (twin, meas, e_paper, pmap) in cases.items():
            params, doc = identify_document(meas, self.geom.sigma_mm, "demo", self.geom)
            full = FullCompensation(params, doc["stiffness_ratio"], self.geom)
            self.fullchain[name] = {
                "before": reached(twin, ph, th, nominal_commands(ph, th, self.geom))["pointing"],
                "seed (HGA, real IK, eq. 7)": held_out(twin, e_paper, None, ph, th, self.geom)["pointing"],
                "seed + fitted position map": held_out(twin, e_paper, pmap, ph, th, self.geom)["pointing"],
                "whole closed chain": reached(twin, ph, th, full.commands_deg(ph, th))["pointing"],
                "_doc": doc, "_params": params, "_full": full}
        first = self.fullchain["Table 2, limbs 1-2"]
        write_params(out / "params_full.json", first["_params"], **first["_doc"])
        self.full_after = first["whole closed chain"]
        self._timed("whole chain", t0)

    def step_render(self, out: Path) -> None:
        from pmcal.mechanism.ocpm.kinematics import nominal_ik

        self.render_png, self.render_note = None, ""
        try:
            from pmcal.twin.render import render_png

            st = self.twin.reach(np.rad2deg(nominal_ik(np.deg2rad(45.0), np.deg2rad(30.0), self.geom)))
            self.render_png = render_png(st.qpos[0], self.twin.errors, width=640, height=480)
        except Exception as exc:            # headless machines without EGL/OSMesa: report without picture
            self.render_note = f"render unavailable: {exc}"

    def step_table(self, out: Path) -> None:
        t0 = time.perf_counter()
        # the table comes from the better model: the whole closed chain (params_full.json)
        full = self.fullchain["Table 2, limbs 1-2"]["_full"]
        self.table = build_table(full.errors, full, self.geom, DEFAULT_GRID, int(time.time()))
        self.table.save(out / "comp_table.json")
        self._timed("table", t0)

    # ------------------------------------------------------------------ outputs
    def summary(self) -> dict:
        b, a = self.before["pointing"], self.full_after
        return {"before_mean_deg": float(b.mean()), "before_max_deg": float(b.max()),
                "after_mean_deg": float(a.mean()), "after_max_deg": float(a.max()),
                "improvement_percent": float(100 * (1 - a.mean() / b.mean())),
                "after_model": "whole closed chain",
                "hga_paper_after_mean_deg": float(self.after["pointing"].mean()),
                "seed_vs_whole_chain": {c: {m: float(v.mean()) for m, v in d.items() if not m.startswith("_")}
                                        for c, d in self.fullchain.items()},
                "methods": {m: {"wall_time_s": d["wall"], "held_out_mean_deg": float(d["held_out"].mean()),
                                "residual_rms_sigma": d["chi_rms"]} for m, d in self.methods.items()},
                "timings_s": self.timings, "table_crc16": f"0x{self.table.crc16():04X}"}


def _stats(a: np.ndarray) -> str:
    return f"mean {np.mean(np.abs(a)):.4f}, max {np.max(np.abs(a)):.4f}"


def demo_report(st: DemoStudy):
    """The demo's self-contained HTML report."""
    from pmcal.report import Report, matplotlib_agg

    matplotlib_agg()
    import matplotlib.pyplot as plt

    from pmcal.mechanism.ocpm.params import PAPER_TABLE2_IDENTIFIED, describe, unit

    rep = Report("pmcal demo: calibration of the over-constrained 2-DoF PM",
                 "Digital twin with the seed's Table 2 errors (limbs 1 and 2), closure compliance, tracker "
                 f"noise {st.geom.sigma_mm} mm; {st.N_CAL} calibration poses, {st.N_TEST} held-out test poses, "
                 f"seed {st.seed}. Method: seed 000 (Sun et al. 2018) sections IV-VI.")
    b, a = st.before["pointing"], st.after["pointing"]
    rep.card("Result", [f"pointing error before: {_stats(b)} deg", f"after (seed HGA method): {_stats(a)} deg",
                        f"after (whole closed chain): {_stats(st.full_after)} deg",
                        f"improvement of the mean: {100 * (1 - a.mean() / b.mean()):.1f} % (seed, experiment: "
                        "93.96 % in theta, 90.38 % in phi)",
                        f"HGA identification of both limbs: {st.cal.wall_time:.2f} s; whole demo "
                        f"{st.timings.get('total', 0):.0f} s"], css="ok")
    rep.heading("The machine")
    if st.render_png:
        rep.image_png(st.render_png, "MuJoCo twin at phi = 45 deg, theta = 30 deg")
    else:
        rep.paragraph(st.render_note or "render unavailable", css="note")
    cl = st.closure
    rep.paragraph(f"Over-constraint: on the calibration poses the passive limbs' closures miss by up to "
                  f"{cl[:, 2:].max():.2f} mm (absorbed by compliance), the actuated ones by "
                  f"{1000 * cl[:, :2].max():.1f} um: the seed's per-limb model is nearly exact for these data.")

    # ---- Table 2
    rep.heading("Identified vs predefined errors (seed Table 2)")
    std = st.cal.uncertainty()
    got = st.cal.params()
    rows = []
    for k in st.cal.names:
        v = got.get(k)
        rows.append([k, describe(k), unit(k), PAPER_TABLE2_IDENTIFIED.get(k, float("nan")), st.truth.get(k, 0.0),
                     float("nan") if v is None else v, float("nan") if std[k] is None else std[k],
                     "unidentifiable" if v is None else f"{(v - st.truth.get(k, 0.0)) / std[k]:+.2f}"])
    rep.table(["key", "meaning", "unit", "seed identified", "predefined", "pmcal HGA", "CRLB std",
               "deviation / std"], rows, left_cols=3,
              caption="Positions mm, angles deg. CRLB: Cramer-Rao standard deviation at 0.01 mm tracker noise.")

    # ---- Fig. 5
    rep.heading("Pointing before and after compensation (seed Fig. 5)")
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.6))
    idx = np.arange(1, st.N_TEST + 1)
    for k, (key, lab) in enumerate((("dtheta", "theta deviation, deg"), ("dphi", "phi deviation, deg"),
                                    ("pointing", "pointing error, deg"))):
        ax[k].plot(idx, st.before[key], "o-", label="before")
        ax[k].plot(idx, st.after[key], "s-", label="after (pmcal)")
        ax[k].set_xlabel("test point")
        ax[k].set_title(lab)
        ax[k].grid(alpha=.3)
    ax[0].legend()
    rep.figure(fig, "Tilt, azimuth and pointing deviations of the 24 test points")
    rep.table(["compensation", "mean pointing, deg", "max pointing, deg", "mean |dtheta|", "mean |dphi|"],
              [[k, v["pointing"].mean(), v["pointing"].max(), np.abs(v["dtheta"]).mean(), np.abs(v["dphi"]).mean()]
               for k, v in st.variants.items()],
              caption="The seed's eq. 7 position limits compensation even with the true errors; the position "
                      "map fitted to the measured platform positions removes that limit.")

    # ---- whole chain
    rep.heading("Seed method vs whole closed chain")
    rows = []
    for case, d in st.fullchain.items():
        for m, v in d.items():
            if not m.startswith("_"):
                rows.append([case, m, v.mean(), v.max(), 100 * (1 - v.mean() / d["before"].mean())])
    rep.table(["machine", "compensation", "mean pointing, deg", "max pointing, deg", "improvement %"], rows,
              left_cols=2, caption="Same 24 calibration poses and 24 held-out test poses for every method. The "
              "whole-chain model (docs/fullchain.md) fits all four limbs, the SS limb and the closure stiffness "
              "ratio to the raw target coordinates; the tracker's own noise floor is ~0.006 deg.")
    fig, ax = plt.subplots(1, len(st.fullchain), figsize=(13, 3.8), sharey=True)
    for a_, (case, d) in zip(np.atleast_1d(ax), st.fullchain.items()):
        for m, v in d.items():
            if not m.startswith("_"):
                a_.semilogy(idx, np.maximum(v, 1e-4), "o-", ms=3, label=m)
        a_.set_title(case, fontsize=9)
        a_.set_xlabel("test point")
        a_.grid(alpha=.3)
    np.atleast_1d(ax)[0].set_ylabel("pointing error, deg")
    np.atleast_1d(ax)[0].legend(fontsize=7)
    rep.figure(fig, "Held-out pointing errors: seed method and whole closed chain")
    doc = st.fullchain["Table 2, limbs 1-2"]["_doc"]
    rep.paragraph(f"Whole-chain fit (Table 2 machine): chi2/dof {doc['fit']['chi2_per_dof']:.3f}, effective "
                  f"parameters {doc['identifiability']['effective_parameters']:.1f} of 55, stiffness ratio "
                  f"{doc['stiffness_ratio']:.3g}, {doc['solver']['wall_time_s']:.2f} s; "
                  f"{len(doc['identifiability']['not_determined_by_campaign'])} parameters held by their priors "
                  "(not determined by this campaign). The compensation table below comes from this model.")

    # ---- Fig. 7-8
    rep.heading("Algorithm comparison (seed Fig. 7-8)")
    rows = []
    for m, d in st.methods.items():
        dev = np.array([d["dev"][k] for k in d["dev"]])
        ang = np.array([unit(k) == "deg" for k in d["dev"]])
        rows.append([m, d["wall"], d["n_eval"], d["chi_rms"], np.max(np.abs(dev[~ang])), np.max(np.abs(dev[ang])),
                     d["held_out"].mean()])
    rep.table(["method", "time, s", "evaluations", "residual rms, sigma", "max |pos. dev|, mm",
               "max |ang. dev|, deg", "held-out pointing, deg"], rows,
              caption="Both limbs, same 24 poses. Deviation: identified minus predefined. Residual 1 = noise level. "
                      "ga/pso/sa ran in two parallel worker processes (times inflated by sharing the CPU); "
                      "clean timings: benchmarks/identify_bench.py.")
    keys = list(st.methods["hga"]["dev"])
    fig, ax = plt.subplots(2, 1, figsize=(13, 6.5))
    width = 0.8 / len(st.methods)
    for i, (m, d) in enumerate(st.methods.items()):
        for row, is_ang in enumerate((False, True)):
            ks = [k for k in keys if (unit(k) == "deg") == is_ang]
            ax[row].bar(np.arange(len(ks)) + i * width, [d["dev"][k] for k in ks], width, label=m)
            ax[row].set_xticks(np.arange(len(ks)) + 0.4, ks, rotation=60, fontsize=7)
    ax[0].set_ylabel("position deviation, mm")
    ax[1].set_ylabel("orientation deviation, deg")
    ax[0].legend(ncol=7, fontsize=8)
    for x in ax:
        x.grid(alpha=.3)
    rep.figure(fig, "Deviation of the identified from the predefined errors per method")

    # ---- Fig. 6
    rep.heading("Regularisation (seed Fig. 6, eq. 18-20)")
    lams, res, sol, corner = st.lcurve
    fig, ax = plt.subplots(1, 2, figsize=(12, 3.8))
    ax[0].loglog(res, sol, "-")
    k = int(np.argmin(np.abs(lams - corner)))
    ax[0].loglog(res[k], sol[k], "ro", label=f"corner, lambda = {corner:.3g}")
    ax[0].set_xlabel("residual norm |H x - dX| (whitened)")
    ax[0].set_ylabel("solution norm (box-scaled)")
    ax[0].legend()
    ax[0].set_title("L-curve")
    for name, d in st.regular.items():
        ax[1].plot(idx, d["held_out"]["pointing"], "o-", label=name)
    ax[1].plot(idx, b, "k:", label="before")
    ax[1].set_xlabel("test point")
    ax[1].set_ylabel("pointing error, deg")
    ax[1].legend(fontsize=8)
    rep.figure(fig, "Tikhonov / TSVD on the seed's linearised pose-error model vs HGA on the real IK model")
    rep.table(["method", "mean pointing, deg", "max pointing, deg", "lambda / rank"],
              [[n, d["held_out"]["pointing"].mean(), d["held_out"]["pointing"].max(),
                "" if d["res"] is None else (f"{d['res'].info['lambda']:.3g}" if "tikhonov" in n
                                             else str(d["res"].info["rank"]))] for n, d in st.regular.items()],
              caption=f"Condition number of the linear model (96 poses, column-normalised): {st.reg_cond:.3g} "
                      "(seed: 6.72e4).")

    # ---- identifiability
    rep.heading("Identifiability")
    lines = []
    for j in (1, 2):
        d, s = st.design[j], st.ident[j]
        lines.append(f"limb {j}: condition number {s.condition_number:.3g} at the solution "
                     f"({d.condition_number:.3g} on the nominal design); weak (CRLB > box): "
                     f"{', '.join(s.weak) or 'none'}")
    for k in st.cal.unidentifiable:
        lines.append(f"{k} is unidentifiable: {pm.explain(k)}. Held at 0.")
    rep.card("Identification Jacobian (whitened, column-normalised)", lines, css="warn")
    fig, ax = plt.subplots(1, 3, figsize=(14, 4))
    for j in (1, 2):
        ax[0].semilogy(st.ident[j].singular_values, "o-", label=f"limb {j}")
    ax[0].set_title("singular values")
    ax[0].legend()
    corr = st.ident[1].correlation
    im = ax[1].imshow(corr, vmin=-1, vmax=1, cmap="RdBu_r")
    ax[1].set_xticks(range(len(st.ident[1].names)), st.ident[1].names, rotation=90, fontsize=7)
    ax[1].set_yticks(range(len(st.ident[1].names)), st.ident[1].names, fontsize=7)
    ax[1].set_title("correlations, limb 1")
    fig.colorbar(im, ax=ax[1])
    ps = st.pose_sel
    n = ps["names"]
    ax[2].semilogy(range(len(n)), ps["random (median of 200)"]["crlb"], "o", label="random 24")
    ax[2].semilogy(range(len(n)), ps["D-optimal (identification)"]["crlb"], "s", label="D-optimal 24")
    ax[2].set_xticks(range(len(n)), n, rotation=90, fontsize=7)
    ax[2].set_title("CRLB std (mm or rad)")
    ax[2].legend()
    rep.figure(fig, "Singular values, correlations, and Cramer-Rao bounds for random vs D-optimal poses")
    rep.heading("Pose selection (seed 003 section 5, generalised)")
    mm_dev = lambda dev: max(abs(v) for k, v in dev.items() if unit(k) == "mm")  # noqa: E731
    rows = [["random (median of 200 draws)", ps["random (median of 200)"]["cond"],
             np.max(ps["random (median of 200)"]["crlb"]), "", ""],
            ["the demo's campaign (spread, random jitter)", st.ident[1].condition_number, "",
             st.after["pointing"].mean(), mm_dev(st.methods["hga"]["dev"])]]
    for label in ("D-optimal (identification)", "D-optimal (identification + position map)"):
        d = ps[label]
        rows.append([label, d["cond"], np.max(d["crlb"]), d["held_out"].mean(), mm_dev(d["dev"])])
    rep.table(["24 poses", "condition number", "max CRLB (mm / rad)", "held-out pointing, deg",
               "max |pos. dev|, mm"], rows,
              caption="Chosen from 600 candidates over theta <= 60 deg on the nominal design (both limbs). "
                      "Identification-only D-optimal poses cluster at the workspace edge: best CRLBs, but the "
                      "position map then extrapolates; the joint criterion keeps both.")

    # ---- table
    rep.heading("Compensation table")
    t = st.table
    rep.paragraph(f"comp_table.json / comp_table.csv: {t.n_phi} x {t.n_theta} nodes over phi "
                  f"{t.phi_min_deg:g}..{t.phi_max_deg:g} deg and theta {t.theta_min_deg:g}..{t.theta_max_deg:g} deg, "
                  f"absolute motor commands in deg, version {t.version}, CRC-16/CCITT 0x{t.crc16():04X}.")
    rep.table(["step", "seconds"], [[k, v] for k, v in st.timings.items()])
    return rep


def run_demo(out: Path, seed: int) -> int:
    """The whole job on the built-in machine with seed Table 2 errors; writes ``out/``."""
    from pmcal.fileio import atomic_directory
    from pmcal.io_ocpm import write_measurements

    t0 = time.perf_counter()
    steps = ["campaign", "identify", "compensate", "fullchain", "algorithms", "regularisation", "identifiability",
             "pose", "render", "table"]
    study = DemoStudy(seed)
    with atomic_directory(out) as tmp:
        with progress.progress(total=len(steps) + 1, desc="pmcal demo", unit="step") as bar:
            for name in steps:
                bar.set_description(f"pmcal demo: {name}")
                getattr(study, f"step_{name}")(tmp)
                bar.update(1)
            bar.set_description("pmcal demo: report")
            write_measurements(tmp / "calibration_meas.csv", study.meas,
                               comments=[f"pmcal demo: twin with seed Table 2 errors, seed {seed}"])
            study.timings["total"] = time.perf_counter() - t0
            summary = study.summary()
            demo_report(study).write(tmp / "report.html")
            write_json(tmp / "summary.json", summary)
            bar.update(1)
    print(f"pmcal demo: wrote {out}/report.html in {time.perf_counter() - t0:.0f} s; mean pointing error on "
          f"{DemoStudy.N_TEST} test poses {summary['before_mean_deg']:.4f} -> {summary['after_mean_deg']:.4f} deg "
          f"({summary['improvement_percent']:.1f} % better, whole closed chain; seed HGA method "
          f"{summary['hga_paper_after_mean_deg']:.4f} deg)")
    return 0


def demo(args) -> int:
    if getattr(args, "hidden_effect", None):           # the discrepancy workflow's demo
        from pmcal.apps.ocpm_diagnose import hidden_effect_demo

        return hidden_effect_demo(args)
    return run_demo(Path(args.out), args.seed)
