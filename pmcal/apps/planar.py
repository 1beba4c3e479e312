"""Application of the planar 2-DOF robot with its measuring mechanism (``--machine planar_2dof``, Mei et al. 2017).

Commands: ``identify`` (zero offsets and MAEMM from a measurement CSV), ``compensate`` (motor commands for
target positions), ``evaluate`` (a parameter set against a measurement CSV), ``twin_measure`` and
``twin_render`` (the MuJoCo twin), ``demo`` (:mod:`pmcal.apps.planar_demo`). Files: mm and degrees
(docs/planar_measurement_format.md); parameter keys: :mod:`pmcal.mechanism.planar.geometry`.
"""

from __future__ import annotations

import math

import numpy as np

from pmcal.commands.options import ABSENT, HIDDEN
from pmcal.errors import InputError, RunError, for_option
from pmcal.option_ranges import parse_task_pose

#: this machine's wording of the commands' options (:mod:`pmcal.commands.options`)
OPTION_HELP = {
    ("twin measure", "--plan"): ABSENT, ("compensate", "--absolute"): ABSENT,
    **{("twin measure", o): HIDDEN for o in ("--stiffness-ratio", "--effect", "--payload", "--temperature",
                                              "--shuffle", "--seconds-per-pose", "--theta-max",
                                              "--no-random-approach", "--tracker-pose", "--nest-error",
                                              "--blocked", "--outliers")},
    **{("identify", o): HIDDEN for o in ("--frame", "--nest-tolerance", "--robust")},
    ("twin render", "--stiffness-ratio"): HIDDEN, ("compensate", "--table"): HIDDEN,
    ("compensate", "--grid"): HIDDEN, ("compensate", "--table-version"): HIDDEN,
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
    ("identify", "--seed"): HIDDEN,
    ("compensate", "--targets"): "targets CSV: x_mm, y_mm ('pmcal --machine planar_2dof targets' writes "
                                 "one)",
    ("compensate", "-o"): "setpoints CSV to write: the targets with theta1_deg, theta2_deg appended",
}


#: defaults of this machine's commands (:attr:`pmcal.machines.Machine.defaults`): 6 positions, the paper's
DEFAULTS = {"poses": 6}


def command_defaults(machine) -> dict:
    """Defaults of the commands (the same for every folder of this machine)."""
    return dict(DEFAULTS)


def option_help(machine) -> dict:
    """The help table of the command line (the same for every folder of this machine)."""
    return OPTION_HELP


MODEL_CHOICES = {None: "simplified", "paper": "simplified", "simplified": "simplified", "full": "full",
                 "chain": "chain"}


def _status(text: str) -> None:
    from pmcal import progress
    progress.status(text)


def _machine():
    from pmcal.twin.planar.config import default_machine
    return default_machine()


def _noise(machine, sigma: float | None):
    from pmcal.mechanism.planar.noise import Noise
    if sigma is None:
        return machine.noise
    if not (math.isfinite(sigma) and sigma > 0):
        raise InputError(f"scale noise must be a positive number of mm, got {sigma}", field="--sigma")
    return Noise(scale=float(sigma), servo=machine.noise.servo)


def identify(args) -> int:
    """``pmcal --machine planar_2dof identify MEAS.csv -o PARAMS.json [--model full] [--method tsvd|ls|gls]``."""
    if getattr(args, "history", None):
        raise InputError("--history files ocpm_2dof calibrations only", field="--history")
    from pmcal.calib.planar.identification import METHODS, identify as run
    from pmcal.campaign_quality import judge
    from pmcal.fileio import write_json
    from pmcal.io_planar import params_document, read_measurements

    machine = _machine()
    model = MODEL_CHOICES.get(getattr(args, "model", None))
    if model is None:
        raise InputError(f"unknown model '{args.model}' (simplified/paper, full or chain)", field="--model")
    if model == "chain":
        return identify_chain_model(args, machine)
    method = getattr(args, "method", None) or machine.calibration.method
    if method not in METHODS:
        raise InputError(f"unknown method '{method}' for planar_2dof ({', '.join(METHODS)})", field="--method")
    meas = read_measurements(args.measurements, machine.geometry)
    n_unknowns = 4 if model == "simplified" else 12
    if len(meas.readings) < n_unknowns:
        raise InputError(f"{len(meas.readings)} readings for {n_unknowns} unknowns of the {model} model",
                         file=meas.path, field="scale_change_mm")
    noise = _noise(machine, getattr(args, "sigma", None))
    res = run(machine.geometry, meas.r, meas.readings, model=model, method=method, segments=meas.segments,
              noise=noise)
    doc = params_document(res, {"n_positions": len(meas.ids), "source": str(args.measurements),
                                "noise": {"scale_sigma_mm": noise.scale,
                                          "servo_sigma_deg": math.degrees(noise.servo)}})
    doc["quality"] = judge(int(doc.get("rank") or 0), len(doc["params"]), what="position", unit="mm")
    deficient = rank_deficiency(machine.geometry, meas, model, doc)
    if deficient and not getattr(args, "allow_rank_deficient", False):
        doc["success"] = False
        doc["message"] = (f"{deficient}; the parameters along the null space are not identified (values and "
                          "uncertainties hold only for the identifiable combinations). --allow-rank-deficient "
                          "accepts the minimum-norm solution")
    write_json(args.output, doc)
    p = doc["params"]
    print(f"{model} model, {method}: dtheta1 = {p['dtheta1']:.4f} deg, dtheta2 = {p['dtheta2']:.4f} deg, "
          f"drM = ({p['drMx']:.3f}, {p['drMy']:.3f}) mm; rank {doc['rank']}, "
          f"cond {doc['condition_number']:.1f} -> {args.output}")
    if deficient and not getattr(args, "allow_rank_deficient", False):
        raise RunError(f"{args.output} written with success false: {deficient} (--allow-rank-deficient "
                       "accepts it)")
    if not doc["success"]:
        from pmcal import progress
        progress.warning(doc["message"])
    return 0


def identify_chain_model(args, machine) -> int:
    """``identify --model chain``: the paper's 12 errors on the generic closed-chain core
    (``mjcf/planar_2dof/chain``: exact model, exact Jacobian, generalised least squares with the servo and
    scale noise, Tikhonov prior) through the closed-form fast path
    (:class:`pmcal.mechanism.planar.chain.PlanarChainModel`, the same numbers as the MuJoCo twin of the folder
    to 1e-9, tests/test_planar_chain_model.py): the identifiable base set is found from the data and the
    combinations it cannot separate are written out (``unidentifiable``)."""
    from pmcal.calib.closed_chain import identify_chain, reading_covariance
    from pmcal.fileio import write_json
    from pmcal.io_planar import MECHANISM, read_measurements
    from pmcal.mechanism.planar.geometry import ERROR_KEYS, interface_unit

    if getattr(args, "method", None):
        raise InputError("--model chain fits by least squares on the exact model (no --method)", field="--method")
    meas = read_measurements(args.measurements, machine.geometry)
    noise = _noise(machine, getattr(args, "sigma", None))
    model = _chain_model(machine)
    cmd = np.rad2deg(meas.theta_cmd)
    servo = [math.degrees(noise.servo)] * 2
    cov = reading_covariance(model, cmd, servo, noise.scale, meas.segments)
    try:
        res = identify_chain(model, cmd, meas.readings, noise.scale, keys=list(ERROR_KEYS), segments=meas.segments,
                             covariance=cov)
    except ValueError as exc:
        raise InputError(str(exc), file=meas.path) from None
    doc = {"mechanism": MECHANISM, "model": "chain", "method": "lm+tikhonov (generic closed-chain core)",
           "params": {k: float(res.params[k]) for k in ERROR_KEYS},
           "units": {k: interface_unit(k) for k in ERROR_KEYS}, "identifiable": list(res.base),
           "uncertainty": dict(res.std), "crlb": dict(res.crlb), "combinations": dict(res.combinations),
           "unidentifiable": list(res.unidentifiable), "weak": list(res.weak), "rank": int(res.rank),
           "condition_number": float(res.condition_number), "residual_rms_mm": float(res.residual_rms_mm),
           "chi2_per_dof": float(res.chi2_per_dof), "n_readings": int(len(meas.readings)),
           "n_positions": len(meas.ids), "source": str(args.measurements), "success": bool(res.success),
           "message": res.message, "noise": {"scale_sigma_mm": noise.scale, "servo_sigma_deg": servo[0]}}
    write_json(args.output, doc)
    p = doc["params"]
    print(f"chain model: {res.rank} of {len(ERROR_KEYS)} errors identifiable (base set); dtheta1 = "
          f"{p['dtheta1']:.4f} deg, dtheta2 = {p['dtheta2']:.4f} deg; residual {res.residual_rms_mm:.4f} mm rms "
          f"-> {args.output}")
    return 0


def rank_deficiency(geom, meas, model: str, doc: dict) -> str:
    """Describe the null space of the identification matrix ``G`` (eq. 24/28) in ``doc`` ("null_space": one
    unit vector per missing rank, keyed by parameter, in the scaled unknowns of eq. 29: mm, and mm per
    link length for the zero offsets); return a one-line summary, or "" when ``G`` has full column rank."""
    from pmcal.calib.planar.identification import MODELS, system

    G, _ = system(geom, meas.r, meas.readings, model, None, meas.segments)
    _, s, Vt = np.linalg.svd(G)
    rank = int(doc.get("rank") or 0)
    n = G.shape[1]
    if rank >= n:
        return ""
    keys = list(MODELS[model])
    null = [{k: round(float(v), 6) for k, v in zip(keys, vec) if abs(v) > 1e-6} for vec in Vt[rank:]]
    doc["null_space"] = null
    biggest = [max(vec, key=lambda k: abs(vec[k])) for vec in null]
    return (f"rank {rank} of {n}: the readings cannot tell {n - rank} combination(s) of the parameters "
            f"apart (largest in {', '.join(dict.fromkeys(biggest))})")


def _chain_model(machine):
    """The generic core's model of this machine: ``mjcf/planar_2dof/chain`` through the paper's closed forms
    (the fast path, :class:`pmcal.mechanism.planar.chain.PlanarChainModel`)."""
    from pmcal.mechanism.machine_spec import MachineSpec
    from pmcal.mechanism.planar.chain import PlanarChainModel
    from pmcal.mjcf import machine_dir

    return PlanarChainModel(MachineSpec.load(machine_dir("planar_2dof") / "chain"), machine.geometry)


def compensate(args) -> int:
    """Motor commands (deg) that bring the identified machine to target positions (mm): the generic core's
    compensation (:func:`pmcal.calib.closed_chain.compensate_targets`: the identified machine's inverse
    kinematics, the zero offsets taken off) on the closed-form fast path (paper section 5)."""
    from pmcal.calib.closed_chain import compensate_targets
    from pmcal.campaign_quality import refuse_unusable
    from pmcal.io_planar import read_params, read_targets, write_setpoints

    if getattr(args, "table", None) or getattr(args, "grid", None):
        raise InputError("compensation tables are not available for planar_2dof", field="--table")
    if not getattr(args, "targets", None) or not getattr(args, "output", None):
        raise InputError("planar_2dof needs --targets TARGETS.csv and -o SETPOINTS.csv", field="--targets")
    machine = _machine()
    errors, doc = read_params(args.params)
    refuse_unusable(doc, str(args.params), bool(getattr(args, "force", False)),
                    fix=f"measure at least {2 * len(errors.as_internal())} positions spread over the workspace "
                        "('pmcal --machine planar_2dof twin measure --poses 24')")
    r, rows, header = read_targets(args.targets, machine.geometry)
    theta = np.deg2rad(compensate_targets(_chain_model(machine), errors.as_interface(), r))
    if not np.all(np.isfinite(theta)):
        row = int(np.flatnonzero(~np.all(np.isfinite(theta), axis=1))[0]) + 1
        raise InputError("out of reach of the identified machine (or outside a motor's range)", file=args.targets,
                         row=row, field="y_mm")
    write_setpoints(args.output, header, rows, theta, comments=[
        f"pmcal compensate, machine planar_2dof, parameters {args.params}", "units: mm, deg"])
    print(f"{len(r)} setpoints for the targets of {args.targets} (machine planar_2dof, parameters {args.params})")
    return 0


def evaluate(args) -> int:
    """How well a parameter set explains a measurement file: RMS of the reading residuals (mm) with the
    nominal machine and with the parameters (the generic core's readings on the closed-form fast path,
    noise-free)."""
    from pmcal.calib.closed_chain import reading_operator
    from pmcal.fileio import write_json
    from pmcal.io_planar import read_measurements, read_params

    machine = _machine()
    errors, _ = read_params(args.params)
    meas = read_measurements(args.measurements, machine.geometry)
    model = _chain_model(machine)
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
    from pmcal.io_planar import read_params
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
    if args.theta_max is not None:
        raise InputError("--theta-max is for ocpm_2dof; planar targets are positions", field="--theta-max")
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
    from pmcal.io_planar import MAX_POSITIONS, read_targets, write_measurements
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
    from pmcal.apps.planar_demo import demo as run
    return run(args)
