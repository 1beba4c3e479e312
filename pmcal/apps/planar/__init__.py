"""Application of the planar 2-DOF robot with its measuring mechanism (``--machine planar_2dof``, Mei et al. 2017).

Commands: ``identify`` (zero offsets and MAEMM from a measurement CSV), ``compensate`` (motor commands for
target positions), ``evaluate`` (a parameter set against a measurement CSV), ``twin_measure`` and
``twin_render`` (the MuJoCo twin), ``demo`` (:mod:`pmcal.apps.planar.demo_run`). Files: mm and degrees
(docs/planar_measurement_format.md); parameter keys: :mod:`pmcal.mechanism.planar.geometry`.
"""

from __future__ import annotations

import math

import numpy as np

from pmcal.errors import InputError, RunError, for_option
from pmcal.option_ranges import parse_task_pose

#: this machine's wording of the commands' options (:mod:`pmcal.commands.options`)
OPTION_HELP = {
    ("twin measure", "--poses"): "number of positions on the workspace boundary, even, 6..2000 (default 6, "
                                 "the paper's)",
    ("twin measure", "--noise"): "linear-scale noise, standard deviation, mm (default the paper's eq. 34)",
    ("twin measure", "--targets"): "explicit target positions (x_mm, y_mm) instead of the boundary layout",
    ("twin measure", "--preset"): "built-in error set: nominal (default) or group1..group6 (the paper's "
                                  "Table 3 groups)",
    ("twin render", "--preset"): "built-in error set: nominal (default) or group1..group6",
    ("twin render", "--pose"): "position X,Y of the platform, mm (seed frame, y < 0)",
    ("identify", "--model"): "error model: the paper's 4 parameters (simplified = paper, default) or all "
                             "12 (full; rank 9, see --allow-rank-deficient)",
    ("identify", "--method"): "tsvd (default, eq. 29), ls (eq. 25) or gls (whitened TSVD)",
    ("identify", "--sigma"): "linear-scale noise, mm (default the paper's eq. 34)",
    ("compensate", "--targets"): "targets CSV: x_mm, y_mm ('pmcal --machine planar_2dof targets' writes "
                                 "one)",
    ("compensate", "-o"): "setpoints CSV to write: the targets with theta1_deg, theta2_deg appended",
}


#: defaults of this machine's commands (:func:`pmcal.commands.routing.command_defaults`): 6 positions, the paper's
DEFAULTS = {"poses": 6}


def command_defaults(machine) -> dict:
    """Defaults of the commands (the same for every folder of this machine)."""
    return dict(DEFAULTS)


def option_help(machine) -> dict:
    """The help table of the command line (the same for every folder of this machine)."""
    return OPTION_HELP


def _status(text: str) -> None:
    from pmcal import progress
    progress.status(text)


def _machine():
    from pmcal.twin.planar.config import default_machine
    return default_machine()


def identify(args) -> int:
    """``pmcal --machine planar_2dof identify MEAS.csv -o PARAMS.json [--model full|chain] [--method tsvd|ls|gls]``:
    :func:`pmcal.planar.calibration.identify`, its document written, one line printed."""
    from pmcal.planar.io import read_measurements
    from pmcal.planar.calibration import identify as run

    meas = read_measurements(args.measurements, _machine().geometry)
    cal = run(meas, model=getattr(args, "model", None), method=getattr(args, "method", None),
              sigma=getattr(args, "sigma", None), allow_rank_deficient=bool(getattr(args, "allow_rank_deficient", False)))
    doc = cal.document
    doc["source"] = str(args.measurements)
    from pmcal.fileio import write_json
    write_json(args.output, doc)
    p = doc["params"]
    if doc["model"] == "chain":
        print(f"chain model: {doc['rank']} of {len(p)} errors identifiable (base set); dtheta1 = "
              f"{p['dtheta1']:.4f} deg, dtheta2 = {p['dtheta2']:.4f} deg; residual {doc['residual_rms_mm']:.4f} mm "
              f"rms -> {args.output}")
        return 0
    print(f"{doc['model']} model, {doc['method']}: dtheta1 = {p['dtheta1']:.4f} deg, dtheta2 = {p['dtheta2']:.4f} "
          f"deg, drM = ({p['drMx']:.3f}, {p['drMy']:.3f}) mm; rank {doc['rank']}, "
          f"cond {doc['condition_number']:.1f} -> {args.output}")
    if cal.deficient:
        raise RunError(f"{args.output} written with success false: {cal.deficient} (--allow-rank-deficient "
                       "accepts it)")
    if not doc["success"]:
        from pmcal import progress
        progress.warning(doc["message"])
    return 0


def compensate(args) -> int:
    """Motor commands (deg) that bring the identified machine to target positions (mm): the generic core's
    compensation (:func:`pmcal.calib.closed_chain.compensate_targets`: the identified machine's inverse
    kinematics, the zero offsets taken off) on the closed-form fast path (paper section 5)."""
    from pmcal.planar.io import read_targets, write_setpoints
    from pmcal.planar.calibration import PlanarCalibration

    if not getattr(args, "targets", None) or not getattr(args, "output", None):
        raise InputError("planar_2dof needs --targets TARGETS.csv and -o SETPOINTS.csv", field="--targets")
    cal = PlanarCalibration.load(args.params)
    r, rows, header = read_targets(args.targets, _machine().geometry)
    try:
        theta = np.deg2rad(cal.setpoints(r, force=bool(getattr(args, "force", False))))
    except InputError as exc:
        if exc.row is None:
            raise
        raise InputError(exc.message, file=args.targets, row=exc.row, field=exc.field) from None
    write_setpoints(args.output, header, rows, theta, comments=[
        f"pmcal compensate, machine planar_2dof, parameters {args.params}", "units: mm, deg"])
    print(f"{len(r)} setpoints for the targets of {args.targets} (machine planar_2dof, parameters {args.params})")
    return 0


def import_campaign(args) -> int:
    """``import`` reads tracker points of nests: this machine is measured by its linear scale."""
    raise InputError("'import' reads tracker points of nests; machine 'planar_2dof' is measured by its linear "
                     "scale, not a tracker", field="--machine")


def export_model(args) -> int:
    """``pmcal --machine planar_2dof export-model PARAMS.json -o MODEL.xml``: the calibrated MJCF of
    ``mjcf/planar_2dof/chain`` and its machine.toml."""
    from pmcal.apps import export_calibrated_model
    from pmcal.planar.calibration import export_parts

    return export_calibrated_model(export_parts(str(args.params)), args, "planar_2dof")


def evaluate(args) -> int:
    """How well a parameter set explains a measurement file: RMS of the reading residuals (mm) with the
    nominal machine and with the parameters (the generic core's readings on the closed-form fast path,
    noise-free)."""
    from pmcal.calib.closed_chain import reading_operator
    from pmcal.fileio import write_json
    from pmcal.planar.io import read_measurements, read_params
    from pmcal.planar.calibration import chain_model

    machine = _machine()
    errors, _ = read_params(args.params)
    meas = read_measurements(args.measurements, machine.geometry)
    model = chain_model(machine)
    D = reading_operator(len(meas.ids), model.reading_reference, meas.segments)
    cmd = np.rad2deg(meas.theta_cmd)

    def residual(params) -> np.ndarray:
        return meas.readings - D @ model.observe(cmd, params)[:, 0]

    before, after = residual(None), residual(errors.as_interface())
    rms = lambda v: float(np.sqrt(np.mean(v * v)))  # noqa: E731
    out = {"mechanism": "planar_2dof", "unit": "mm", "n_readings": int(len(before)),
           "rms_nominal": rms(before), "rms_params": rms(after), "max_abs_params": float(np.max(np.abs(after)))}
    print(f"reading residual RMS: nominal {out['rms_nominal']:.4f} mm, with parameters {out['rms_params']:.4f} mm")
    if getattr(args, "json", None):
        write_json(args.json, out)
    return 0


def _errors_from_args(args, machine):
    from pmcal.planar.io import read_params
    if getattr(args, "errors", None):
        with for_option("--errors"):
            errors, _ = read_params(args.errors, require_mechanism=False)
        return errors, str(args.errors)
    name = getattr(args, "preset", None) or "nominal"
    return machine.preset(name), f"preset {name}"


def targets(args) -> int:
    """``pmcal --machine planar_2dof targets -o TARGETS.csv``: ``--count`` positions (mm, seed frame) on the
    boundary of the paper's workspace (Fig. 7), the layout the identification uses."""
    from pmcal.calib.planar.design import boundary_positions
    from pmcal.csvio import write_csv

    if not 2 <= args.count <= 100_000:
        raise InputError(f"count must be 2..100000, got {args.count}", field="--count")
    machine = _machine()
    r = boundary_positions(machine.workspace, (args.count + 1) // 2)[: args.count]
    write_csv(args.output, ["x_mm", "y_mm"], ([f"{x:.4f}", f"{y:.4f}"] for x, y in r),
              [f"pmcal targets: machine planar_2dof, {len(r)} positions on the workspace boundary",
               "units: mm; seed frame O-xy, y up, the platform below the base (y < 0); docs/formats.md"])
    print(f"targets: machine planar_2dof, {len(r)} positions on the workspace boundary")
    return 0


def twin_measure(args) -> int:
    """A virtual campaign: ``--poses K`` positions (paper Fig. 7, K even) or ``--targets``; scale noise
    ``--noise`` (mm, default eq. 34) and servo noise (eq. 35); readings as in the measurement CSV."""
    from pmcal.calib.planar.design import boundary_positions
    from pmcal.mechanism.planar.noise import Noise
    from pmcal import progress
    from pmcal.planar.io import MAX_POSITIONS, read_targets, write_measurements
    from pmcal.twin.planar.twin import PlanarTwin, commands_for, measure

    machine = _machine()
    errors, source = _errors_from_args(args, machine)
    sigma = getattr(args, "noise", None)
    noise = machine.noise if sigma is None else Noise(scale=float(sigma), servo=machine.noise.servo)
    if not (math.isfinite(noise.scale) and noise.scale >= 0):
        raise InputError(f"noise must be a non-negative number of mm, got {sigma}", field="--noise")
    servo = getattr(args, "servo_noise", None)
    if servo is not None:
        if not (math.isfinite(servo) and servo >= 0):
            raise InputError(f"servo noise must be a non-negative number of degrees, got {servo}",
                             field="--servo-noise")
        noise = Noise(scale=noise.scale, servo=math.radians(servo))
    if getattr(args, "targets", None):
        r, _, _ = read_targets(args.targets, machine.geometry)
        if len(r) < 2:
            raise InputError("a campaign needs at least two positions", file=args.targets, field="x_mm")
    else:
        poses = getattr(args, "poses", None)
        K = int(DEFAULTS["poses"] if poses is None else poses)
        if K < 6 or K % 2 or K > MAX_POSITIONS:
            raise InputError(f"number of poses must be even and 6..{MAX_POSITIONS} (K = 2n > 5; the most identify "
                             f"reads), got {K}", field="--poses")
        r = boundary_positions(machine.workspace, K // 2)
    twin = PlanarTwin(errors, machine)
    rng = np.random.default_rng(int(getattr(args, "seed", 1)))
    progress.status(f"measuring {len(r)} positions on the planar twin")
    camp = measure(twin, commands_for(twin, r), noise, rng)
    write_measurements(args.output, camp.theta_cmd[0], camp.readings[0], targets=r, comments=[
        f"pmcal twin measure: machine planar_2dof, errors: {source}, positions {len(r)}, "
        f"scale sigma {noise.scale:.4g} mm, servo sigma {math.degrees(noise.servo):.4g} deg, "
        f"seed {getattr(args, 'seed', 1)}",
        "units: mm, deg; seed frame O-xy (y up); scale_change_mm = change since the previous row"])
    print(f"measured {len(r)} positions on the twin of planar_2dof (errors: {source}, scale sigma "
          f"{noise.scale:.4g} mm, seed {getattr(args, 'seed', 1)})")
    return 0


def twin_render(args) -> int:
    """PNG of the twin; ``--pose X,Y`` is the position of P in mm (the default ``0,0`` means home P0)."""
    from pmcal.mechanism.planar.kinematics import inverse
    from pmcal.fileio import atomic_write
    from pmcal.twin.planar.twin import PlanarTwin, render_png
    from pmcal.twin.render import RenderUnavailable

    machine = _machine()
    errors, _ = _errors_from_args(args, machine)
    text = getattr(args, "pose", None) or "0,0"
    x, y = (float(v) for v in parse_task_pose(text, ("X", "Y")))
    motor = machine.geometry.home if (x, y) == (0.0, 0.0) else inverse(machine.geometry, np.array([x, y]))
    if not np.all(np.isfinite(motor)) or y > 0:
        raise InputError(f"position ({x:g}, {y:g}) mm is out of the robot's reach (y < 0 below the base)",
                         field="--pose")
    try:
        png = render_png(PlanarTwin(errors, machine), motor, width=getattr(args, "width", 800),
                         height=getattr(args, "height", 600))
    except RenderUnavailable as exc:
        raise RunError(str(exc)) from None
    with atomic_write(args.output, "wb") as fh:
        fh.write(png)
    _status(f"picture -> {args.output}")
    return 0


def demo(args) -> int:
    from pmcal.apps.planar.demo_run import demo as run
    return run(args)
