"""The demo's study: a virtual campaign on the twin with the paper's Table 2 errors, identification with
the paper's method and the whole closed chain, compensation, method comparison, regularisation,
identifiability, pose selection, a picture and the PLC table. Units: mm and degrees.

:class:`DemoStudy` computes and keeps the results; :mod:`pmcal.reports.ocpm.demo` turns them into the HTML
report; ``pmcal demo`` (:func:`run_demo`) writes the folder.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from pmcal import progress
from pmcal.calib.ocpm import compensation as comp
from pmcal.calib.ocpm import paper_calibration
from pmcal.calib.ocpm import paper_model as pm
from pmcal.calib.solvers import METHODS
from pmcal.ocpm.calibration import identify
from pmcal.ocpm.compensators import DEFAULT_GRID, PaperCompensation, build_table, checked_commands, deg
from pmcal.fileio import write_json
from pmcal.reports.ocpm.demo import demo_report
from pmcal.studies.ocpm.demo_tracker import tracker_run
from pmcal.ocpm.io import write_setpoints
from pmcal.mechanism.ocpm.config import Geometry, default_geometry
from pmcal.mechanism.ocpm.params import ErrorSet
from pmcal.mechanism.rotations import pointing_error, tilt_torsion, tilt_torsion_angles


def _paper_fit(meas, rng_seed: int):
    """(per-limb paper calibration, fitted position map) with HGA."""
    c = identify(meas, model="paper", method="hga", rng_seed=rng_seed)
    return c.solution, c.compensator.pmap


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
    """Pointing errors on test poses after the paper's compensation with ``errors`` and ``pmap``."""
    m = PaperCompensation(errors, pmap, geom).commands_deg(phi_deg, theta_deg)
    return reached(twin, phi_deg, theta_deg, m)


def parameter_errors(cal, truth: dict[str, float]) -> dict[str, float]:
    """Identified minus predefined, interface units (mm, deg), identifiable parameters only."""
    got = cal.params()
    return {k: got[k] - truth.get(k, 0.0) for k in cal.names if k in got}


#: Budgets of the population methods in the quick demo (``pmcal demo``; ``--full`` and
#: benchmarks/identify_bench.py run them to their own stopping rules): about a tenth of their full cost.
QUICK_BUDGETS: dict[str, dict] = {"ga": {"max_gen": 150}, "pso": {"max_iter": 150}, "sa": {"maxfun": 2000}}
#: The slow methods, slowest first: submitted first so none waits for the others at the end.
SLOW_FIRST = ("sa", "ga", "pso")


def _timed_calibration(meas, method: str, seed: int, options: dict | None = None):
    """(calibration, wall time) of one method on both limbs (a worker-process entry point)."""
    from pmcal.threads import apply_blas_policy

    apply_blas_policy()
    t0 = time.perf_counter()
    cal = paper_calibration.calibrate(meas, method, seed=seed, **(options or {}))
    return cal, time.perf_counter() - t0


def _render(truth: dict, geom: Geometry) -> tuple[bytes | None, str]:
    """(PNG of the twin at phi 45, theta 30 deg, note): a worker-process entry point (EGL start-up ~2 s)."""
    from pmcal.mechanism.ocpm.kinematics import nominal_ik

    try:
        from pmcal.twin.ocpm.machine import Twin
        from pmcal.twin.ocpm.machine import render_png

        twin = Twin(truth, geom)
        st = twin.reach(np.rad2deg(nominal_ik(np.deg2rad(45.0), np.deg2rad(30.0), geom)))
        return render_png(st.qpos[0], twin.errors, width=640, height=480), ""
    except Exception as exc:            # headless machines without EGL/OSMesa: report without picture
        return None, f"render unavailable: {exc}"


def _pose_study(seed: int, theta_max: float, unidentifiable: list[str], truth: dict, test_phi, test_theta,
                n_cal: int, geom: Geometry) -> dict:
    """Random vs D-optimal calibration poses (condition number, CRLB, held-out pointing): the demo's pose
    selection step, a worker-process entry point."""
    from pmcal.calib.pose_selection import condition_number, crlb_std, join_blocks, select_poses
    from pmcal.threads import apply_blas_policy
    from pmcal.twin.ocpm.campaign import CampaignPlan, plan_orientations, run_campaign
    from pmcal.twin.ocpm.machine import Twin
    from pmcal.twin.tracker import LaserTracker

    apply_blas_policy()
    twin = Twin(truth, geom)
    rng = np.random.default_rng(seed + 3000)
    ph, th = plan_orientations(600, theta_max, rng)
    names = [k for k in pm.param_names() if k not in unidentifiable]
    B = pm.design_blocks(np.deg2rad(ph), np.deg2rad(th), names, geom=geom)
    B_joint = join_blocks(B, comp.position_map_blocks(np.deg2rad(ph), np.deg2rad(th)))
    rand = [rng.choice(len(ph), n_cal, replace=False) for _ in range(200)]
    pose_sel = {"names": names, "random (median of 200)": {
        "cond": float(np.median([condition_number(B, i) for i in rand])),
        "crlb": np.median([crlb_std(B, i) for i in rand], axis=0)}}
    for label, blocks in (("D-optimal (identification)", B), ("D-optimal (identification + position map)",
                                                               B_joint)):
        sel = select_poses(blocks, n_cal, "D")
        plan = CampaignPlan(phi_deg=ph[sel], theta_deg=th[sel], approach=np.ones((n_cal, 2)),
                            time_s=np.arange(n_cal) * 30.0)
        meas = run_campaign(twin, plan, LaserTracker(geom.sigma_mm, np.random.default_rng(seed + 4000)))
        cal, pmap = _paper_fit(meas, seed)
        pose_sel[label] = {
            "cond": condition_number(B, sel), "crlb": crlb_std(B, sel), "dev": parameter_errors(cal, truth),
            "held_out": held_out(twin, cal.errors(), pmap, test_phi, test_theta, geom)["pointing"]}
    return pose_sel


class DemoStudy:
    """The demo's computations, one method per step; results kept for the report (mm, deg)."""

    N_CAL = 24
    N_TEST = 24
    N_REG = 96            # the paper's regularisation study uses 96 poses (section VI-A)
    METHODS_COMPARED: tuple[str, ...] = METHODS

    def __init__(self, seed: int, full: bool = False, pool=None):
        from pmcal.mechanism.ocpm.params import PAPER_TABLE2
        from pmcal.twin.ocpm.machine import Twin

        self.full, self.pool = full, pool            # pool: a 2-worker process pool for the slow steps
        self.budgets = {} if full else QUICK_BUDGETS
        self._futures: dict = {}
        self.seed, self.geom = seed, default_geometry()
        self.truth = dict(PAPER_TABLE2)
        self.twin = Twin(self.truth)
        self.theta_max = deg(self.geom.theta_max)
        self.timings: dict[str, float] = {}
        self.methods: dict[str, dict] = {}

    def _timed(self, name: str, t0: float) -> None:
        self.timings[name] = time.perf_counter() - t0

    def campaign(self, n: int, seed: int, theta_max: float | None = None, plan=None):
        from pmcal.twin.ocpm.campaign import plan_campaign, run_campaign
        from pmcal.twin.tracker import LaserTracker

        plan = plan or plan_campaign(n, theta_max or self.theta_max, seed)
        return run_campaign(self.twin, plan, LaserTracker(self.geom.sigma_mm, np.random.default_rng(seed)))

    # ------------------------------------------------------------------ steps
    def step_campaign(self, out: Path) -> None:
        from pmcal.twin.ocpm.campaign import plan_campaign

        t0 = time.perf_counter()
        from pmcal.twin.ocpm.campaign import plan_campaign as _plan

        self.meas_plan = _plan(self.N_CAL, self.theta_max, self.seed)
        self.meas = self.campaign(self.N_CAL, self.seed, plan=self.meas_plan)
        self.test = plan_campaign(self.N_TEST, self.theta_max, self.seed + 1000)
        r, R, _ = self.meas.poses(self.geom)
        st = self.twin.reach(self.meas.m_cmd_deg)
        self.closure = st.closure_residual                     # (N, 4) mm
        self._timed("campaign", t0)
        if self.pool is not None:                              # the slowest method first
            self._submit_methods(SLOW_FIRST[:1])
            self._futures["tracker"] = self.pool.submit(tracker_run, *self._tracker_args(out))

    def _submit_methods(self, methods) -> None:
        for m in methods:
            if m in self.METHODS_COMPARED:
                self._futures[m] = self.pool.submit(_timed_calibration, self.meas, m, self.seed, self.budgets.get(m))

    def step_identify(self, out: Path) -> None:
        t0 = time.perf_counter()
        self.calibration = identify(self.meas, model="paper", method="hga", rng_seed=self.seed)
        self.cal, self.pmap = self.calibration.solution, self.calibration.compensator.pmap
        self._timed("identify", t0)
        self.calibration.document["source"] = "calibration_meas.csv"
        self.calibration.save(out / "params.json")
        self.params_doc = self.calibration.document
        if self.pool is not None:                              # then pose selection, the rest, the picture
            self._futures["pose"] = self.pool.submit(_pose_study, *self._pose_args())
            self._submit_methods(SLOW_FIRST[1:])
            self._futures["render"] = self.pool.submit(_render, self.truth, self.geom)

    def step_compensate(self, out: Path) -> None:
        from pmcal.twin.ocpm.campaign import nominal_commands

        t0 = time.perf_counter()
        ph, th = self.test.phi_deg, self.test.theta_deg
        e_hat, e_true = self.cal.errors(), ErrorSet.from_dict(self.truth)
        m_before = nominal_commands(ph, th, self.geom)
        m_after = checked_commands(PaperCompensation(e_hat, self.pmap, self.geom), ph, th, self.geom)
        write_setpoints(out / "test_setpoints.csv", ph, th, m_after,
                        comments=["pmcal demo: compensated commands of the 24 test poses"])
        lin = np.rad2deg(comp.linear_commands_rad(np.deg2rad(ph), np.deg2rad(th), e_hat, self.geom))
        eq7 = np.rad2deg(comp.ik_commands_rad(np.deg2rad(ph), np.deg2rad(th), e_hat, self.geom))
        eq7_true = np.rad2deg(comp.ik_commands_rad(np.deg2rad(ph), np.deg2rad(th), e_true, self.geom))
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
        """Every method on the same data; the slow population methods run in the worker processes (with
        the budgets :data:`QUICK_BUDGETS` unless ``full``), started right after the campaign."""
        t0 = time.perf_counter()
        slow = [m for m in self.METHODS_COMPARED if m in SLOW_FIRST]
        runs = {m: _timed_calibration(self.meas, m, self.seed) for m in self.METHODS_COMPARED
                if m not in slow and m != "hga"}
        for m in slow:
            f = self._futures.pop(m, None)
            runs[m] = f.result() if f is not None else _timed_calibration(self.meas, m, self.seed,
                                                                            self.budgets.get(m))
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
        t0 = time.perf_counter()
        f = self._futures.pop("pose", None)
        self.pose_sel = f.result() if f is not None else _pose_study(*self._pose_args())
        self._timed("pose selection", t0)

    def _pose_args(self) -> tuple:
        return (self.seed, self.theta_max, list(self.cal.unidentifiable), self.truth, self.test.phi_deg,
                self.test.theta_deg, self.N_CAL, self.geom)

    def step_fullchain(self, out: Path) -> None:
        """Paper method vs whole closed chain on the same data: Table 2 errors in limbs 1-2, and the same
        machine with 0.5 mm / 0.1 deg (1 sigma) errors added to the passive limbs and the SS limb."""
        from pmcal.mechanism.ocpm.params import random_errors
        from pmcal.twin.ocpm.campaign import nominal_commands, run_campaign
        from pmcal.twin.ocpm.machine import Twin
        from pmcal.twin.tracker import LaserTracker

        t0 = time.perf_counter()
        ph, th = self.test.phi_deg, self.test.theta_deg
        extra = random_errors(np.random.default_rng(self.seed + 5000), 0.5, 0.1, limbs=(3, 4),
                              distribution="normal")
        cases = {"Table 2, limbs 1-2": (self.twin, self.meas, self.cal.errors(), self.pmap)}
        twin2 = Twin({**self.truth, **extra})
        meas2 = run_campaign(twin2, self.meas_plan, LaserTracker(self.geom.sigma_mm, np.random.default_rng(self.seed)))
        cal2, pmap2 = _paper_fit(meas2, self.seed)
        cases["Table 2 + passive limbs and SS (0.5 mm / 0.1 deg)"] = (twin2, meas2, cal2.errors(), pmap2)
        self.fullchain = {}
        for name, (twin, meas, e_paper, pmap) in cases.items():
            cal_full = identify(meas, source="demo")
            full = cal_full.compensator
            self.fullchain[name] = {
                "before": reached(twin, ph, th, nominal_commands(ph, th, self.geom))["pointing"],
                "seed (HGA, real IK, eq. 7)": held_out(twin, e_paper, None, ph, th, self.geom)["pointing"],
                "seed + fitted position map": held_out(twin, e_paper, pmap, ph, th, self.geom)["pointing"],
                "whole closed chain": reached(twin, ph, th, full.commands_deg(ph, th))["pointing"],
                "_calibration": cal_full, "_full": full}
        first = self.fullchain["Table 2, limbs 1-2"]
        first["_calibration"].save(out / "params_full.json")
        self.full_after = first["whole closed chain"]
        self._timed("whole chain", t0)

    def _tracker_args(self, out: Path) -> tuple:
        return (self.truth, self.meas_plan, self.seed, self.geom, self.test.phi_deg, self.test.theta_deg,
                out / "params_tracker.json")

    def step_tracker(self, out: Path) -> None:
        """The demo's campaign measured by a tracker in its own frame (nests off, blocked targets, one
        outlier), identified with the registration: :func:`pmcal.studies.ocpm.demo_tracker.tracker_run`."""
        t0 = time.perf_counter()
        f = self._futures.pop("tracker", None)
        self.tracker = f.result() if f is not None else tracker_run(*self._tracker_args(out))
        self._timed("tracker frame", t0)

    def step_render(self, out: Path) -> None:
        f = self._futures.pop("render", None)
        self.render_png, self.render_note = f.result() if f is not None else _render(self.truth, self.geom)

    def step_table(self, out: Path) -> None:
        t0 = time.perf_counter()
        # the table comes from the better model: the whole closed chain (params_full.json)
        full = self.fullchain["Table 2, limbs 1-2"]["_full"]
        self.table = build_table(full, self.geom, DEFAULT_GRID, int(time.time()))
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
                "paper_vs_whole_chain": {c: {m: float(v.mean()) for m, v in d.items() if not m.startswith("_")}
                                        for c, d in self.fullchain.items()},
                "methods": {m: {"wall_time_s": d["wall"], "held_out_mean_deg": float(d["held_out"].mean()),
                                "residual_rms_sigma": d["chi_rms"]} for m, d in self.methods.items()},
                "tracker_frame": self.tracker_summary(),
                "population_method_budgets": self.budgets or "full",
                "timings_s": self.timings, "table_crc32": f"0x{self.table.crc32():08X}"}


    def tracker_summary(self) -> dict:
        """The tracker-frame run in figures (:func:`pmcal.studies.ocpm.demo_tracker.summary`)."""
        from pmcal.studies.ocpm.demo_tracker import summary

        return summary(self.tracker)


def run_demo(out: Path, seed: int, full: bool = False) -> int:
    """The whole job on the built-in machine with paper Table 2 errors; writes ``out/``.

    The population methods' comparison and the picture run in two worker processes started at once;
    without ``full`` the population methods get the budgets :data:`QUICK_BUDGETS` (the report says so).
    """
    from pmcal.fileio import atomic_directory
    from pmcal.ocpm.io import write_measurements
    from pmcal.studies.workers import worker_pool

    t0 = time.perf_counter()
    steps = ["campaign", "identify", "compensate", "fullchain", "regularisation", "identifiability",
             "table", "tracker", "pose", "algorithms", "render"]
    with worker_pool(2) as pool, atomic_directory(out) as tmp:     # Ctrl-C: workers killed, not waited for
        study = DemoStudy(seed, full, pool)
        with progress.progress(total=len(steps) + 1, desc="pmcal demo", unit="step") as bar:
            for name in steps:
                bar.set_description(f"pmcal demo: {name}")
                getattr(study, f"step_{name}")(tmp)
                bar.update(1)
            bar.set_description("pmcal demo: report")
            write_measurements(tmp / "calibration_meas.csv", study.meas,
                               comments=[f"pmcal demo: twin with paper Table 2 errors, seed {seed}"])
            study.timings["total"] = time.perf_counter() - t0
            summary = study.summary()
            demo_report(study, pool).write(tmp / "report.html")
            write_json(tmp / "summary.json", summary)
            bar.update(1)
    print(f"pmcal demo: {out}/report.html in {time.perf_counter() - t0:.0f} s; mean pointing error on "
          f"{DemoStudy.N_TEST} test poses {summary['before_mean_deg']:.4f} -> {summary['after_mean_deg']:.4f} deg "
          f"({summary['improvement_percent']:.1f} % better, whole closed chain; paper HGA method "
          f"{summary['hga_paper_after_mean_deg']:.4f} deg)", flush=True)
    return 0
