"""The commands of a machine folder (routed from :mod:`pmcal.apps.chain`): ``twin measure``, ``identify``,
``targets``, ``compensate``, ``evaluate``. Thin handlers over :mod:`pmcal.chain`; files in
:mod:`pmcal.io_chain` (docs/formats.md, "Any machine"). Units: mm and degrees.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from pmcal import progress
from pmcal.apps import error_stats
from pmcal.apps.chain import ERROR_CHOICES, command_defaults
from pmcal.campaign_quality import refuse_unusable, save_table
from pmcal.chain import (campaign, campaign_quality, check_assembles, compensate as commands_for, compensation_table,
                         dominant_line, identify as run_identification, params_document, reference_basis, residuals,
                         sample_targets, table_refusal)
from pmcal.csvio import LONG_POSES
from pmcal.errors import InputError, for_option
from pmcal.fileio import read_json, write_json
from pmcal.history import chain_record_document, check_history_dir, file_calibration
from pmcal.twin.overconstraint import loop_summary
from pmcal.io_chain import (read_measurements, read_params, read_plan, read_targets, write_measurements,
                            write_setpoints, write_targets)


def _machine(args):
    return args.selected_machine


def _sigma(value: float | None, option: str) -> float | None:
    if value is not None and not (np.isfinite(value) and value >= 0):
        raise InputError(f"noise must be a non-negative number of mm, got {value}", field=option)
    return value


def error_set(machine, text: str | None):
    """``--errors``: random (default), none, or a parameters file of this machine."""
    if text is None or text in ERROR_CHOICES:
        return text or "random"
    if not Path(text).is_file():
        raise InputError(f"'{text}' is neither {' nor '.join(ERROR_CHOICES)} nor a parameters file",
                         field="--errors")
    with for_option("--errors"):
        params, _ = read_params(text, machine.spec, _units(machine))
    return params


def _units(machine) -> dict[str, str]:
    twin = machine.twin
    return dict(zip(twin.error_keys, twin.error_units()))


def twin_measure(args) -> int:
    """``pmcal --machine DIR twin measure --poses N --seed S -o MEAS.csv``: a virtual campaign on the twin
    with random geometric errors (or ``--errors``) and the tracker noise of machine.toml (or ``--noise``)."""
    machine = _machine(args)
    if args.poses is not None and not 1 <= args.poses <= 2000:
        raise InputError(f"number of poses must be 1..2000, got {args.poses}", field="--poses")
    if not (np.isfinite(args.seconds_per_pose) and args.seconds_per_pose >= 0):
        raise InputError(f"seconds per pose must be >= 0, got {args.seconds_per_pose}", field="--seconds-per-pose")
    sigma = _sigma(args.noise, "--noise")
    if args.targets and args.plan:
        raise InputError("give --targets or --plan, not both", field="--plan")
    task = read_targets(args.targets, machine.spec) if args.targets else None
    ids, commands = read_plan(args.plan, machine.spec) if args.plan else (None, None)
    errors = error_set(machine, args.errors)
    poses = args.poses or command_defaults(machine)["poses"]
    count = len(task) if task is not None else len(commands) if commands is not None else poses
    progress.status(f"measuring {count} poses on the twin of {machine.name}")
    meas, truth = campaign(machine, poses, seed=args.seed, errors=errors, sigma_mm=sigma, task=task,
                           commands=commands, pose_id=ids, seconds_per_pose=args.seconds_per_pose,
                           source=args.targets or args.plan)
    what = args.errors if isinstance(errors, dict) else errors
    comments = [f"pmcal twin measure: machine {machine.name}, errors: {what}, poses {len(meas)}, tracker sigma "
                f"{machine.twin.sigma_mm if sigma is None else sigma:g} mm, seed {args.seed}"]
    if truth:
        comments.append("true errors (mm, deg): " + ", ".join(f"{k}={v:.6g}" for k, v in truth.items()))
    write_measurements(args.output, machine.spec, meas, comments)
    print(f"measured {len(meas)} poses on the twin of {machine.name} (errors: {what}, tracker sigma "
          f"{machine.twin.sigma_mm if sigma is None else sigma:g} mm, seed {args.seed})")
    return 0


def identify(args) -> int:
    """``pmcal --machine DIR identify MEAS.csv -o PARAMS.json [--sigma MM]``: the geometric errors the
    campaign determines (base set), their uncertainty and what the data cannot see."""
    machine = _machine(args)
    sigma = _sigma(args.sigma, "--sigma")
    if sigma == 0:
        raise InputError("tracker noise must be positive", field="--sigma")
    history = getattr(args, "history", None)
    if history:
        check_history_dir(history)
    meas = read_measurements(args.measurements, machine.spec)
    progress.set_long(len(meas) > LONG_POSES)
    progress.status(f"identifying {len(machine.twin.error_keys)} errors of {machine.name} from {len(meas)} poses")
    partial = [pid for pid, row in zip(meas.pose_id, meas.targets) if np.isnan(row).any()]
    # filed into a history: in the machine's structural base set, the same for every campaign
    basis = reference_basis(machine) if history else None
    res = run_identification(machine, meas, sigma, basis)
    if partial:
        progress.warning(f"{len(partial)} pose(s) with a blocked target left out ({', '.join(partial[:3])}"
                         f"{', ...' if len(partial) > 3 else ''}): identification uses the poses with every "
                         "target measured")
    quality = campaign_quality(machine, meas, res, sigma, reference=basis)
    doc = params_document(machine, res, str(args.measurements))
    write_json(args.output, dict(doc, quality=quality))
    print(f"{res.rank} of {len(res.params)} errors identifiable (base set), {len(res.weak)} weak; residual "
          f"{res.residual_rms_mm:.4f} mm rms, chi2/dof {res.chi2_per_dof:.2f}; "
          f"{'usable' if quality['usable'] else 'NOT usable'}")
    loops = loop_summary(machine.twin)
    if loops["redundant"]:
        print(f"loops: {loops['closure_equations']} closure equations, {loops['independent']} independent; "
              f"redundant ({', '.join(loops['redundant'])}) left to the joints' play")
    if history:
        file_history(machine, res, basis, args.measurements, history)
    for line in identify_warnings(res, len(meas), outliers=bool(quality["outliers"])):
        progress.warning(line)
    unseen = doc["unseen_by_tracker"]
    if unseen:
        progress.warning(f"{len(unseen)} error(s) move the task point but no tracker reading "
                         f"({', '.join(unseen[:4])}{', ...' if len(unseen) > 4 else ''}): the compensation cannot "
                         "correct them (the predicted task error counts them at their [errors] size); put a nest "
                         "on that part, or list it under [errors] exclude if its geometry is known")
    dominant = dominant_line(doc["dominant_task_uncertainty"], unseen)
    if dominant:
        progress.warning(dominant)
    if not quality["usable"]:
        progress.warning(f"calibration not usable: {quality['why']}; compensate and push refuse it without --force "
                         "('pmcal twin plan' with this --machine plans a campaign)")
    return 0


#: chi2 per degree of freedom above which the model does not explain the data down to the tracker noise
CHI2_WARN = 2.0


def file_history(machine, res, basis, campaign: str, folder: str) -> None:
    """File an identification made in the machine's structural base set ``basis``
    (:func:`pmcal.chain.reference_basis`) into a history folder; a campaign that determines fewer of its
    combinations is not filed (a warning says why: its record could not be compared)."""
    if res.info.get("basis") != "given":
        progress.warning(f"not filed into {folder}: the campaign determines {res.rank} of the machine's "
                         f"{basis.rank} identifiable combinations (measure more poses spread over the workspace, "
                         f"e.g. 'pmcal --machine {machine.name} twin plan')")
        return
    record = chain_record_document(res, campaign, machine.name)
    print(f"pmcal: wrote {file_calibration(record, folder)}")


#: more poses of the same kind are advised for the directions the prior sets when at most this many would
#: determine them (a long day of tracker work at 30 s a pose); beyond it a nest elsewhere or fewer error frames
MORE_POSES_HELP = 1000


def _prior_set_warning(res, n_poses: int) -> str:
    """The warning for base parameters the prior sets (``res.weak``): how many directions of the base set the
    poses know less of than the prior (``info["prior_set"]``, :func:`pmcal.calib.closed_chain.
    prior_set_directions`), which errors lean on them, and whether more poses of the same kind would help."""
    names = f"{', '.join(res.weak[:3])}{', ...' if len(res.weak) > 3 else ''}"
    dirs = res.info.get("prior_set") or {}
    k, need = dirs.get("count", 0), dirs.get("poses_needed", 0)
    if not k:
        return (f"{len(res.weak)} of the {res.rank} identifiable errors are set by the prior, not by the {n_poses} "
                f"poses ({names}): measure more poses spread over the workspace")
    head = (f"{k} of the {res.rank} identifiable directions are set by the prior, not by the {n_poses} poses "
            f"({len(res.weak)} errors have a part in them: {names})")
    if need <= MORE_POSES_HELP:
        return f"{head}: measure more poses spread over the workspace"
    many = "no number of poses would" if not np.isfinite(need) else \
        f"at the rate these {n_poses} poses add information, about {need:.2g} would"
    return (f"{head}: more poses of the same kind hardly help ({many} determine them); the prior keeps them "
            "at their [errors] size, which the predicted uncertainty counts. A tracker nest elsewhere on the moving "
            "parts may see them; [errors] frames you know to be exact can be left out")


def identify_warnings(res, n_poses: int, outliers: bool = False) -> list[str]:
    """What a user must know about an identification that still succeeded (docs/ADDING_A_MACHINE.md,
    "When fewer errors are identifiable than expected"); with ``outliers`` (gross outliers found, named
    by the quality verdict) the high chi2 is theirs and not reported again."""
    out = []
    if not res.success:
        out.append(f"the fit did not converge: {res.message}")
    if res.weak:
        out.append(_prior_set_warning(res, n_poses))
    if res.chi2_per_dof > CHI2_WARN and not outliers:
        out.append(f"the model leaves {res.residual_rms_mm:.4f} mm rms (chi2/dof {res.chi2_per_dof:.1f}, "
                   f"{res.sigma_mm:g} mm tracker noise): an error frame missing from [errors], a wrong "
                   "sigma_mm, or an effect the geometry does not hold")
    far = res.info.get("beyond_prior") or []
    if far:
        out.append(f"{len(far)} base value(s) identified beyond 5 sigma of their [errors] prior "
                   f"({', '.join(far[:3])}{', ...' if len(far) > 3 else ''}): an error far larger than the drawing's "
                   "tolerance, or an effect the geometry does not hold absorbed into it")
    return out


def targets(args) -> int:
    """``pmcal --machine DIR targets -o TARGETS.csv``: ``--count`` targets over the workspace of machine.toml."""
    machine = _machine(args)
    if not 1 <= args.count <= 100_000:
        raise InputError(f"count must be 1..100000, got {args.count}", field="--count")
    task = sample_targets(machine, args.count, args.seed)
    what = f"machine {machine.name}, {args.count} targets over the workspace of machine.toml, seed {args.seed}"
    write_targets(args.output, machine.spec, task, [f"pmcal targets: {what}"])
    print(f"targets: {what}")
    return 0


def compensate(args) -> int:
    """``pmcal --machine DIR compensate PARAMS.json --targets TARGETS.csv -o SETPOINTS.csv``: offline
    compensation of a target list (the identified machine's inverse kinematics)."""
    machine = _machine(args)
    if getattr(args, "table", None):
        return _table(args, machine)
    if getattr(args, "grid", None) or getattr(args, "table_version", None) or getattr(args, "absolute", False):
        raise InputError("--grid, --table-version and --absolute go with --table TABLE.json", field="--grid")
    if not args.targets or not args.output:
        raise InputError(f"machine {machine.name} needs --targets TARGETS.csv and -o SETPOINTS.csv",
                         field="--targets" if not args.targets else "-o")
    params = _usable_params(args, machine)
    task = read_targets(args.targets, machine.spec)
    progress.status(f"compensating {len(task)} targets")
    commands = commands_for(machine, params, task, args.targets)
    write_setpoints(args.output, machine.spec, task, commands,
                    [f"pmcal compensate: machine {machine.name}, parameters {args.params}"])
    print(f"{len(task)} setpoints for the targets of {args.targets} (machine {machine.name}, parameters {args.params})")
    return 0


def export_model(args) -> int:
    """``pmcal --machine DIR export-model PARAMS.json -o MODEL.xml``: the folder's calibrated MJCF and
    machine.toml (never written into the machine folder)."""
    from pmcal.apps import export_calibrated_model
    from pmcal.export_model import chain_parts

    machine = _machine(args)
    return export_calibrated_model(chain_parts(str(args.params), machine), args, machine.name, keep=machine.folder)


def import_campaign(args) -> int:
    """``pmcal --machine DIR import TRACKER LOG -o MEAS.csv``: the folder's measurement CSV from a tracker
    export and the controller log with its motor columns (:func:`pmcal.io_tracker.join_machine`)."""
    from pmcal.apps import import_tracker_campaign
    from pmcal.chain import distance_from_nominal
    from pmcal.csvio import PLAUSIBLE_TARGET_DISTANCE_TRACKER_MM, check_nest_distances
    from pmcal.io_chain import check_commands
    from pmcal.io_tracker import export_pose_errors, join_machine, read_controller_log

    machine = _machine(args)
    spec = machine.spec

    def joined(export):
        log = read_controller_log(args.log, spec.motor_columns)
        check_commands(log.commands, spec, log.path, spec.motor_columns)   # the log's rows, not the output's
        res = join_machine(export, log, spec, lambda c, t: distance_from_nominal(machine, c, t), names=args.names,
                           time_tolerance_s=args.time_tolerance)
        if len(spec.targets) > 1:      # the nests' distances against the machine's, as ocpm_2dof's import checks
            with export_pose_errors(res.meas, args.tracker, args.units):
                check_nest_distances(res.meas.targets, machine.twin.targets(res.meas.commands), args.tracker,
                                     PLAUSIBLE_TARGET_DISTANCE_TRACKER_MM)
        return res

    return import_tracker_campaign(
        args, joined,
        lambda res: write_measurements(args.output, spec, res.meas, comments=res.comments),
        "transform them into the base frame (the frame of the MJCF's world) before identifying")


def evaluate(args) -> int:
    """``pmcal --machine DIR evaluate PARAMS.json MEAS.csv [--json OUT.json]``: how far the measured targets
    are from where the machine with those parameters puts them (mm)."""
    machine = _machine(args)
    params, _ = read_params(args.params, machine.spec, _units(machine))
    meas = read_measurements(args.measurements, machine.spec)
    check_assembles(machine, meas)
    d = residuals(machine, params, meas)
    stats = error_stats(d)
    what = "reading error" if machine.spec.measure == "distance" else "target position error"
    print(f"{what} over {len(meas)} poses: rms {stats['rms']:.4f} mm, max {stats['max']:.4f} mm")
    if args.json:
        per_pose = [{"pose_id": pid, "position_error_mm": [None if np.isnan(v) else float(v) for v in row]}
                    for pid, row in zip(meas.pose_id, d)]
        write_json(args.json, {"mechanism": machine.name, "params_file": str(args.params),
                               "measurements": str(args.measurements), "unit": "mm", "n_poses": len(meas),
                               "position_error_mm": stats, "per_pose": per_pose})
    return 0


def _table(args, machine) -> int:
    """``compensate PARAMS.json --table TABLE.json [--grid N1,N2,N3] [--table-version V] [--absolute]``: the
    format-4 compensation table over the machine's [table] axes (docs/compensation_table.md), JSON and CSV
    beside: corrections to the controller's own nominal IK, or with ``--absolute`` motor commands."""
    why = table_refusal(machine)
    if why:
        raise InputError(why, field="--table")
    if args.targets:
        raise InputError("--table writes a table over the [table] grid; --targets is for target lists",
                         field="--targets")
    version = int(time.time()) if args.table_version is None else args.table_version
    if not 1 <= version <= 2**32 - 1:
        raise InputError(f"table version {version} outside 1..4294967295", field="--table-version")
    params = _usable_params(args, machine)
    table = compensation_table(machine, params, version, parse_nodes(args.grid),
                               absolute=True if args.absolute else None)
    save_table(table, args.table, read_json(args.params).get("quality"))
    shape = "x".join(map(str, table.shape))
    kind = ("corrections to add to the controller's nominal IK (nReference 2)" if table.controller_reference
            else "absolute motor commands")
    print(f"compensation table version {version}: {shape} nodes over {', '.join(a.column for a in table.axes)}, "
          f"{table.n_motors} motors, {kind}, CRC-32 0x{table.crc32():08X}")
    return 0


def _usable_params(args, machine) -> dict[str, float]:
    """The parameters of ``args.params``, refused (unless ``--force``) when identify flagged them not usable:
    the verdict is read first, so a fit spoiled by an outlier is refused for its outlier, not for a value."""
    doc = read_json(args.params)
    if isinstance(doc, dict) and doc.get("mechanism") == machine.name:
        fix = ("measure poses spread over the workspace ('pmcal twin plan' with this --machine plans them) and "
               "remeasure or delete outlier rows")
        refuse_unusable(doc, str(args.params), bool(getattr(args, "force", False)), fix)
    params, _ = read_params(args.params, machine.spec, _units(machine))
    return params


def parse_nodes(text: str | None) -> list[int] | None:
    """``--grid N1,N2,..``: table nodes per [table] axis, or None (machine.toml's ``[table] nodes``); the
    counts themselves are checked by :func:`pmcal.chain.compensation_table`."""
    if not text:
        return None
    try:
        return [int(v) for v in str(text).split(",")]
    except ValueError:
        raise InputError(f"expected node counts N1,N2,.. (integers), got '{text}'", field="--grid") from None
