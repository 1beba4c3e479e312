"""``pmcal identify | compensate | evaluate | demo`` for the over-constrained PM: thin handlers over the
library (:mod:`pmcal.ocpm.calibration`, :mod:`pmcal.ocpm.compensators`, :mod:`pmcal.studies.ocpm.demo`).

File formats: ``docs/formats.md`` (mm and degrees). Each handler reads and validates the input, calls the
library, and writes its outputs atomically after everything was computed.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from pmcal import progress
from pmcal.apps import error_stats
from pmcal.campaign_quality import CAMPAIGN_FIX, quality_line, refuse_unusable, save_table
from pmcal.ocpm.calibration import Calibration, identify as identify_campaign, record_document
from pmcal.ocpm.compensators import DEFAULT_GRID, PaperCompensation, build_table, check_grid, checked_commands
from pmcal.errors import InputError
from pmcal.fileio import write_json
from pmcal.history import check_history_dir, file_calibration
from pmcal.ocpm.io import LONG_POSES, MECHANISM, read_measurements, read_targets, write_setpoints
from pmcal.mechanism.ocpm.config import default_geometry
from pmcal.mechanism.ocpm.kinematics import real_ik_commands
from pmcal.mechanism.rotations import pointing_error, tilt_torsion, tilt_torsion_angles


def parse_grid(text: str | None) -> tuple[int, int]:
    """``NPHI,NTHETA`` of ``--grid`` (default 73,31), within the PLC's array size."""
    if text is None:
        return DEFAULT_GRID
    try:
        grid = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"expected NPHI,NTHETA (two integers), got '{text}'", field="--grid") from None
    return check_grid(grid)


# ====================================================================== identify
#: Base-frame (motor axes) uncertainty of a tracker-frame fit above which identify points to the
#: designed campaign (48 designed poses to 80 deg give ~0.003 deg, docs/tracker_frame.md).
FRAME_HINT_DEG = 0.004


def identify(args) -> int:
    from pmcal.ocpm.tracker_frame import check_nest_tolerance, parse_frame, warn_rejected

    frame, reg0 = parse_frame(getattr(args, "frame", None))
    nest_std = check_nest_tolerance(getattr(args, "nest_tolerance", None))
    history = getattr(args, "history", None)
    if history:
        check_history_dir(history)
    meas = read_measurements(args.measurements, default_geometry(), frame=frame)
    progress.set_long(len(meas) > LONG_POSES)
    if (args.model or "full") == "full" and args.method is None:
        progress.status(f"identifying the whole closed chain from {len(meas)} poses ({frame} frame)")
    cal = identify_campaign(meas, model=args.model or "full", method=args.method, sigma_mm=args.sigma,
                            rng_seed=args.seed, source=str(args.measurements), frame=frame, registration=reg0,
                            nest_tolerance_mm=nest_std, robust=True if getattr(args, "robust", False) else None)
    warn_rejected(cal.document)
    if "registration" in cal.document:
        std = float(np.linalg.norm(cal.document["registration"]["std_rot_deg"]))
        line = f"base frame (motor axes) determined to {std:.4f} deg (1 sigma)"
        if std > FRAME_HINT_DEG:
            progress.warning(line + "; 48 designed poses ('pmcal twin plan --frame tracker --poses 48') fix it "
                             "to ~0.003 deg (docs/tracker_frame.md)")
        else:
            progress.status(line)
    cal.save(args.output)
    fit = cal.document["fit"]
    quality = (f"chi2/dof {fit['chi2_per_dof']:.3g}" if cal.model == "full" else
               f"residual {fit['residual_rms_sigma']:.3g} sigma")
    q = cal.document["quality"]
    print(f"identified {len(cal.params)} parameters ({'whole chain' if cal.model == 'full' else cal.method}); "
          f"{quality}; {quality_line(q)}", flush=True)
    if history:
        print(f"pmcal: wrote {file_calibration(record_document(cal, args.measurements), history)}")
    if not q["usable"]:
        progress.warning(f"this calibration is not usable: {q['why']}; {CAMPAIGN_FIX} (compensate and push "
                         "refuse it without --force)")
    return 0


# ====================================================================== compensate
def compensate(args) -> int:
    from pmcal.twin.ocpm.campaign import THETA_LIMIT_DEG

    if not args.targets and not args.table:
        raise InputError("nothing to do: give --targets TARGETS.csv -o SETPOINTS.csv and/or --table TABLE.json",
                         field="--targets")
    if args.targets and not args.output:
        raise InputError("--targets needs -o SETPOINTS.csv", field="-o")
    if args.output and not args.targets:
        raise InputError("-o SETPOINTS.csv needs --targets TARGETS.csv", field="--targets")
    cal = Calibration.load(args.params)
    refuse_unusable(cal.document, str(args.params), bool(getattr(args, "force", False)))
    grid = parse_grid(args.grid)
    version = getattr(args, "table_version", None)
    version = int(time.time()) if version is None else int(version)
    work = []                                          # compute everything before writing anything
    if args.targets:
        phi, theta = read_targets(args.targets, theta_max_deg=THETA_LIMIT_DEG)
        m = checked_commands(cal.compensator, phi, theta, cal.geometry, args.targets)
        note = f"pmcal compensate: {args.params}, {cal.compensator.description}"
        work.append(lambda: write_setpoints(args.output, phi, theta, m, comments=[note]))
        print(f"{len(phi)} setpoints for the targets of {args.targets} ({cal.compensator.description})")
    if args.table:
        progress.status(f"computing the compensation table: {grid[0]} x {grid[1]} orientations")
        table = build_table(cal.compensator, cal.geometry, grid, version)
        work.append(lambda: save_table(table, args.table, cal.document.get("quality")))
    for w in work:
        w()
    return 0


# ====================================================================== evaluate
def evaluate_params(meas, cal: Calibration) -> dict:
    """Where the calibrated model says the commands go vs where the platform was measured."""
    geom, c = cal.geometry, cal.compensator
    r, R, _ = meas.poses(geom)
    phi, theta = c.orientation(meas.m_cmd_deg)
    if isinstance(c, PaperCompensation):               # the paper's model: real IK at the measured pose
        motor = np.rad2deg(real_ik_commands(r, R, c.errors, geom)) - meas.m_cmd_deg
    else:                                              # whole chain: the inverse of the forward model
        phi_m, theta_m = tilt_torsion_angles(R)
        motor = c.commands_deg(np.rad2deg(phi_m), np.rad2deg(theta_m)) - meas.m_cmd_deg
    err = np.rad2deg(pointing_error(tilt_torsion(phi, theta), R))
    return {"n_poses": len(meas), "pointing_error_deg": error_stats(err),
            "motor_residual_deg": {"m1": error_stats(motor[:, 0]), "m2": error_stats(motor[:, 1])},
            "per_pose": [{"pose_id": pid, "pointing_error_deg": float(e), "m1_residual_deg": float(a),
                          "m2_residual_deg": float(b)} for pid, e, (a, b) in zip(meas.pose_id, err, motor)]}


def evaluate(args) -> int:
    cal = Calibration.load(args.params)
    meas = read_measurements(args.measurements, cal.geometry)
    out = evaluate_params(meas, cal)
    c = cal.compensator
    position = "whole closed chain" if not isinstance(c, PaperCompensation) else (
        "fitted map" if c.pmap is not None else "nominal (eq. 7)")
    out = {"mechanism": MECHANISM, "params_file": str(args.params), "measurements": str(args.measurements),
           "model": cal.model, "position": position, "unit": "deg", **out}
    pe = out["pointing_error_deg"]
    print(f"pointing error over {out['n_poses']} poses: rms {pe['rms']:.4f} deg, max {pe['max']:.4f} deg")
    if args.json:
        write_json(args.json, out)
    return 0


# ====================================================================== demo
def demo(args) -> int:
    if getattr(args, "hidden_effect", None):           # the discrepancy workflow's demo: its own folder
        from pmcal.apps.ocpm.diagnosis import hidden_effect_demo

        return hidden_effect_demo(args)
    from pmcal.studies.ocpm.demo import run_demo

    return run_demo(Path(args.out), args.seed, full=getattr(args, "full", False))


def export_model(args) -> int:
    """``pmcal export-model PARAMS.json -o MODEL.xml``: ocpm_2dof's calibrated MJCF and machine.toml."""
    from pmcal.apps import export_calibrated_model
    from pmcal.ocpm.calibration import export_parts

    return export_calibrated_model(export_parts(str(args.params)), args, MECHANISM)


def import_campaign(args) -> int:
    """``pmcal import TRACKER LOG -o MEAS.csv``: ocpm_2dof's measurement CSV from a tracker export and the
    controller log (:func:`pmcal.ocpm.io.join`); the nests' distances are checked against the platform's
    before anything is written (points in metres are refused here, not blamed on the frame later)."""
    from pmcal.apps import import_tracker_campaign
    from pmcal.ocpm.io import check_plausible, join, write_measurements
    from pmcal.io_tracker import export_pose_errors, read_controller_log

    def joined(export):
        res = join(export, read_controller_log(args.log), names=args.names, time_tolerance_s=args.time_tolerance)
        with export_pose_errors(res.meas, args.tracker, args.units):
            check_plausible(res.meas, default_geometry(), args.tracker, "tracker")
        return res

    return import_tracker_campaign(
        args, joined, lambda res: write_measurements(args.output, res.meas, comments=res.comments),
        f"identify with 'pmcal identify {args.output} --frame tracker' (recorded in its header)")
