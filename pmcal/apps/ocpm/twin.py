"""``pmcal twin measure|render`` for the over-constrained PM."""

from __future__ import annotations

import numpy as np

from pmcal.mechanism.ocpm.config import default_geometry
from pmcal.mechanism.ocpm.params import PAPER_TABLE2
from pmcal import progress
from pmcal.apps.ocpm import DEFAULTS
from pmcal.errors import InputError, RunError, for_option
from pmcal.fileio import atomic_write
from pmcal.ocpm.io import MAX_POSES, read_campaign_context, read_params, read_targets, write_measurements
from pmcal.option_ranges import parse_task_pose

PRESETS: dict[str, dict[str, float]] = {"paper-table2": PAPER_TABLE2, "nominal": {}}


def machine_errors(args) -> dict[str, float]:
    """The error set selected by ``--preset`` / ``--errors`` (default: nominal)."""
    if getattr(args, "errors", None):
        with for_option("--errors"):
            params, _ = read_params(args.errors)
        return params
    name = getattr(args, "preset", None) or "nominal"
    if name not in PRESETS:
        raise InputError(f"unknown preset '{name}' (known: {', '.join(PRESETS)})", field="--preset")
    return dict(PRESETS[name])


def build_twin(args, errors: dict[str, float]):
    from pmcal.twin.ocpm.machine import Twin

    return Twin(errors, stiffness_ratio=stiffness_ratio(args))


def stiffness_ratio(args) -> float | None:
    """``--stiffness-ratio`` checked (None: the machine's default)."""
    ratio = getattr(args, "stiffness_ratio", None)
    if ratio is not None and not (np.isfinite(ratio) and ratio > 0):
        raise InputError(f"stiffness ratio must be a positive number, got {ratio}", field="--stiffness-ratio")
    return ratio


def targets(args) -> int:
    """``pmcal targets -o TARGETS.csv``: ``--count`` orientations spread over the tilt cap (deg)."""
    from pmcal.csvio import write_csv
    from pmcal.twin.ocpm.campaign import THETA_LIMIT_DEG, plan_orientations

    if not 1 <= args.count <= 100_000:
        raise InputError(f"count must be 1..100000, got {args.count}", field="--count")
    theta_max = 60.0 if args.theta_max is None else args.theta_max
    if not 0 < theta_max <= THETA_LIMIT_DEG:
        raise InputError(f"tilt limit {theta_max:g} deg is outside 0..{THETA_LIMIT_DEG:g} deg", field="--theta-max")
    phi, theta = plan_orientations(args.count, theta_max, np.random.default_rng(args.seed))
    what = f"machine ocpm_2dof, {args.count} orientations up to {theta_max:g} deg tilt, seed {args.seed}"
    write_csv(args.output, ["phi_deg", "theta_deg"], ([f"{p:.4f}", f"{t:.4f}"] for p, t in zip(phi, theta)),
              [f"pmcal targets: {what}", "units: deg; phi = azimuth of the tilt axis, theta = tilt (docs/formats.md)"])
    print(f"targets: {what}")
    return 0


def twin_measure(args) -> int:
    from pmcal.twin.ocpm.campaign import THETA_LIMIT_DEG, CampaignPlan, plan_campaign, run_campaign
    from pmcal.twin.tracker import LaserTracker

    geom = default_geometry()
    sigma = geom.sigma_mm if args.noise is None else args.noise
    if not np.isfinite(sigma) or sigma < 0:
        raise InputError(f"noise must be a non-negative number of mm, got {args.noise}", field="--noise")
    if args.poses is None:
        args.poses = DEFAULTS["poses"]
    if not 1 <= args.poses <= MAX_POSES:
        raise InputError(f"number of poses must be 1..{MAX_POSES} (the most identify and diagnose read), got "
                         f"{args.poses}", field="--poses")
    theta_max = np.rad2deg(geom.theta_max) if args.theta_max is None else args.theta_max
    if not 0 < theta_max <= THETA_LIMIT_DEG:
        raise InputError(f"tilt limit {theta_max:g} deg is outside the workspace 0..{THETA_LIMIT_DEG:g} deg "
                         "(the RSR limbs reach their stretched-link singularity near 87.5 deg)",
                         field="--theta-max")
    errors = machine_errors(args)
    tracker_pose, faults = tracker_setup(args)
    context = read_campaign_context(args.targets) if args.targets else {}
    if effect_campaign_requested(args) or context:
        return measure_with_effects(args, errors, sigma, theta_max, tracker_pose, faults, context)
    plan = plan_campaign(args.poses, theta_max, args.seed, randomize_approach=not args.no_random_approach)
    if args.targets:
        phi, theta = read_targets(args.targets, theta_max_deg=THETA_LIMIT_DEG)
        n = len(phi)
        plan = CampaignPlan(phi_deg=phi, theta_deg=theta, approach=plan_campaign(
            n, theta_max, args.seed, randomize_approach=not args.no_random_approach).approach,
            time_s=np.arange(n) * 30.0)
    try:
        twin = build_twin(args, errors)
    except ValueError as exc:
        raise InputError(str(exc), file=args.errors, field="params") from None
    rng = np.random.default_rng(args.seed)
    progress.status(f"measuring {len(plan)} poses on the twin (σ = {sigma:g} mm)")
    try:
        meas = run_campaign(twin, plan, LaserTracker(sigma, rng, pose=tracker_pose), faults=faults)
    except ValueError as exc:
        raise InputError(str(exc), file=args.targets, field="theta_deg" if args.targets else "--poses") from None
    except RuntimeError as exc:          # the closed chain of this machine cannot close at a pose
        raise RunError(f"{exc}: the machine cannot reach that pose (lower --theta-max)") from None
    source = args.errors or f"preset {args.preset or 'nominal'}"
    write_measurements(args.output, meas, comments=[
        f"pmcal twin measure: machine {geom_name()}, errors: {source}, poses {len(meas)}, "
        f"tracker sigma {sigma:g} mm, seed {args.seed}",
        "units: mm, deg; targets in the " + ("tracker frame" if tracker_pose is not None else "base frame O-xyz")]
        + truth_comments(tracker_pose, meas))
    print(f"measured {len(meas)} poses on the twin of {geom_name()} (errors: {source}, tracker sigma {sigma:g} mm, "
          f"seed {args.seed})")
    return 0


def tracker_setup(args):
    """``--tracker-pose``, ``--nest-error``, ``--blocked``, ``--outliers`` checked: (pose or None, faults
    or None)."""
    from scipy.spatial.transform import Rotation

    from pmcal.twin.ocpm.campaign import MeasurementFaults
    from pmcal.twin.tracker import random_tracker_pose

    pose = None
    text = getattr(args, "tracker_pose", None)
    if text == "random":
        pose = random_tracker_pose(np.random.default_rng([args.seed, 16]))
    elif text:
        v = parse_numbers(text, 6, "--tracker-pose", "X,Y,Z,RX,RY,RZ (mm, deg) or 'random'")
        pose = (Rotation.from_rotvec(v[3:], degrees=True).as_matrix(), v[:3])
    nest = getattr(args, "nest_error", 0.0) or 0.0
    blocked = getattr(args, "blocked", 0.0) or 0.0
    if not (np.isfinite(nest) and 0 <= nest <= 5):
        raise InputError(f"nest error must be 0..5 mm, got {nest}", field="--nest-error")
    if not (np.isfinite(blocked) and 0 <= blocked <= 1):
        raise InputError(f"blocked probability must be 0..1, got {blocked}", field="--blocked")
    n_out, out_mm = 0, 2.0
    if getattr(args, "outliers", None):
        n_text, _, mm_text = args.outliers.partition(":")
        try:
            n_out, out_mm = int(n_text), float(mm_text) if mm_text else 2.0
        except ValueError:
            raise InputError(f"expected N or N:MM, got '{args.outliers}'", field="--outliers") from None
        if n_out < 0 or not np.isfinite(out_mm):
            raise InputError(f"expected a non-negative count and a finite size, got '{args.outliers}'",
                             field="--outliers")
    if not (nest or blocked or n_out):
        return pose, None
    return pose, MeasurementFaults(nest_error_mm=nest, blocked=blocked, outliers=n_out, outlier_mm=out_mm,
                                   seed=args.seed + 16)


def parse_numbers(text: str, n: int, field: str, what: str) -> np.ndarray:
    try:
        v = np.array([float(x) for x in text.split(",")])
    except ValueError:
        v = np.array([])
    if v.shape != (n,) or not np.isfinite(v).all():
        raise InputError(f"expected {what}, got '{text}'", field=field)
    return v


def truth_comments(pose, meas) -> list[str]:
    """What the twin did, for checking a calibration (comment lines; readers skip them)."""
    from scipy.spatial.transform import Rotation

    out = []
    if pose is not None:
        rv = Rotation.from_matrix(pose[0]).as_rotvec(degrees=True)
        out.append("truth tracker pose (base in tracker; mm, rotvec deg): "
                   + ",".join(f"{v:.6f}" for v in np.r_[pose[1], rv]))
    if "nest_offsets" in meas.extra:
        out.append("truth nest offsets (platform frame, mm): "
                   + ",".join(f"{v:.5f}" for v in meas.extra["nest_offsets"][0].reshape(-1)))
        for i, k, a in np.argwhere(meas.extra["outlier"] != 0):
            out.append(f"truth outlier: row {i + 1} target t{k + 1} axis {'xyz'[a]} "
                       f"{meas.extra['outlier'][i, k, a]:+.3f} mm")
    return out


def effect_campaign_requested(args) -> bool:
    """Effects or context (payload, temperature, order) asked for: the effect-aware twin measures."""
    return bool(getattr(args, "effect", None) or getattr(args, "payload", None) or getattr(args, "temperature", None)
                or getattr(args, "shuffle", False))


def parse_levels(text: str | None, field: str, lo: float, hi: float, unit: str, most: int | None = None):
    """Comma-separated numbers within [lo, hi] (None when not given)."""
    if text is None:
        return None
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"expected comma-separated numbers ({unit}), got '{text}'", field=field) from None
    if not vals or (most is not None and len(vals) > most):
        raise InputError(f"expected 1{'..' + str(most) if most else ' or more'} values, got '{text}'", field=field)
    bad = [v for v in vals if not (np.isfinite(v) and lo <= v <= hi)]
    if bad:
        raise InputError(f"{bad[0]:g} {unit} is outside {lo:g}..{hi:g} {unit}", field=field)
    return vals


def measure_with_effects(args, errors: dict[str, float], sigma: float, theta_max: float,
                         tracker_pose=None, faults=None, context: dict[str, np.ndarray] | None = None) -> int:
    """``twin measure`` with effects: the effect-aware twin (gravity, payload, temperature, drive effects),
    measured by a tracker at ``tracker_pose`` (None: in the base frame) through ``faults`` (nests, blocked
    targets, outliers; :func:`tracker_setup`); ``context``: the campaign columns of the targets file
    (:func:`pmcal.ocpm.io.read_campaign_context`), driven in the file's order."""
    from pmcal.apps.ocpm.effect_scenarios import parse_effects
    from pmcal.twin.ocpm.effects import EffectTwin, plan_effect_campaign
    from pmcal.twin.tracker import LaserTracker

    try:
        effects = parse_effects(args.effect)
    except ValueError as exc:
        raise InputError(str(exc), field="--effect") from None
    payloads = parse_levels(args.payload, "--payload", 0.0, 100.0, "kg") or (0.0,)
    temps = parse_levels(args.temperature, "--temperature", -20.0, 80.0, "degC", most=2)
    context = context or {}
    # a campaign file's payload and temperature columns, and its order, are the campaign's own
    clashes = [(c, o) for c, o, given in (("payload_kg", "--payload", args.payload),
                                          ("temp_c", "--temperature", temps)) if given and c in context]
    if context and args.shuffle:
        clashes.append((next(iter(context)), "--shuffle"))
    if clashes:
        column, option = clashes[0]
        raise InputError(f"{args.targets} is a campaign with a {column} column (driven in its own order, "
                         f"with its own context): drop {option}", field=option)
    if effects.thermal_expansion is not None and temps is None and "temp_c" not in context:
        raise InputError("thermal_expansion needs the machine temperature: give --temperature (e.g. 18,28)",
                         field="--effect")
    if not (np.isfinite(args.seconds_per_pose) and args.seconds_per_pose > 0):
        raise InputError(f"seconds per pose must be positive, got {args.seconds_per_pose}", field="--seconds-per-pose")
    n = args.poses
    phi = theta = None
    if args.targets:
        from pmcal.twin.ocpm.campaign import THETA_LIMIT_DEG
        phi, theta = read_targets(args.targets, theta_max_deg=THETA_LIMIT_DEG)
        n = len(phi)
    plan = plan_effect_campaign(n, theta_max, args.seed, payloads=payloads, temp_c=temps,
                                shuffle=args.shuffle, randomize_approach=not args.no_random_approach,
                                seconds_per_pose=args.seconds_per_pose)
    if phi is not None:
        order = np.random.default_rng([args.seed, 8]).permutation(n) if args.shuffle else np.arange(n)
        plan.phi_deg, plan.theta_deg = phi[order], theta[order]
        # a campaign file (pmcal twin plan --for-diagnosis) brings its own context, in its own order
        plan.payload_kg = context.get("payload_kg", plan.payload_kg)
        plan.temp_c = context.get("temp_c", plan.temp_c)
        plan.time_s = context.get("time_s", plan.time_s)
        plan.approach = context.get("approach", plan.approach)
    try:
        twin = EffectTwin(errors, effects, stiffness_ratio=stiffness_ratio(args), seed=args.seed)
    except ValueError as exc:
        raise InputError(str(exc), file=args.errors, field="params") from None
    progress.status(f"measuring {len(plan)} poses on the twin with {', '.join(effects.active()) or 'no effects'}")
    try:
        meas = twin.measure(plan, LaserTracker(sigma, np.random.default_rng(args.seed), pose=tracker_pose),
                            faults=faults)
    except ValueError as exc:
        raise InputError(str(exc), file=args.targets, field="theta_deg" if args.targets else "--poses") from None
    except RuntimeError as exc:
        raise RunError(f"{exc}: the machine cannot reach that pose (lower --theta-max)") from None
    source = args.errors or f"preset {args.preset or 'nominal'}"
    active = ", ".join(f"{k}={v}" for k, v in effects.values().items()) or "none"
    write_measurements(args.output, meas, comments=[
        f"pmcal twin measure: machine {geom_name()}, errors: {source}, poses {len(meas)}, tracker sigma "
        f"{sigma:g} mm, seed {args.seed}, gravity on, effects: {active}",
        "units: mm, deg, degC, kg, s; targets in the "
        + ("tracker frame" if tracker_pose is not None else "base frame O-xyz")] + truth_comments(tracker_pose, meas))
    print(f"measured {len(meas)} poses on the twin of {geom_name()} (errors: {source}, tracker sigma {sigma:g} mm, "
          f"seed {args.seed}, effects: {active})")
    return 0


def geom_name() -> str:
    return "ocpm_2dof"


def parse_pose(text: str) -> tuple[float, float]:
    """``--pose PHI,THETA`` in degrees: two finite numbers, the azimuth within -360..360 deg."""
    phi, theta = parse_task_pose(text, ("PHI", "THETA"))
    if abs(phi) > 360:
        raise InputError(f"azimuth {phi:g} deg is outside -360..360 deg", field="--pose")
    return float(phi), float(theta)


def twin_render(args) -> int:
    from pmcal.mechanism.ocpm.kinematics import nominal_ik
    from pmcal.twin.ocpm.campaign import THETA_LIMIT_DEG
    from pmcal.twin.ocpm.machine import render_png
    from pmcal.twin.render import RenderUnavailable

    phi, theta = parse_pose(args.pose)
    if not 0 <= theta <= THETA_LIMIT_DEG:
        raise InputError(f"tilt {theta:g} deg is outside 0..{THETA_LIMIT_DEG:g} deg", field="--pose")
    errors = machine_errors(args)
    twin = build_twin(args, errors)
    m_cmd = np.rad2deg(nominal_ik(np.deg2rad(phi), np.deg2rad(theta)))
    state = twin.reach(m_cmd)
    try:
        png = render_png(state.qpos[0], twin.errors, width=args.width, height=args.height)
    except RenderUnavailable as exc:
        raise RunError(str(exc)) from None
    with atomic_write(args.output, "wb") as fh:
        fh.write(png)
    return 0
