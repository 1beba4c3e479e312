"""``pmcal twin measure|render`` for the over-constrained PM."""

from __future__ import annotations

import numpy as np

from calib.ocpm.config import default_geometry
from calib.ocpm.params import PAPER_TABLE2
from pmcal import progress
from pmcal.errors import InputError, RunError
from pmcal.fileio import atomic_write
from pmcal.io_ocpm import read_params, read_targets, write_measurements

PRESETS: dict[str, dict[str, float]] = {"paper-table2": PAPER_TABLE2, "nominal": {}}


def machine_errors(args) -> dict[str, float]:
    """The error set selected by ``--preset`` / ``--errors`` (default: nominal)."""
    if getattr(args, "errors", None):
        params, _ = read_params(args.errors)
        return params
    name = getattr(args, "preset", None) or "nominal"
    if name not in PRESETS:
        raise InputError(f"unknown preset '{name}' (known: {', '.join(PRESETS)})", field="--preset")
    return dict(PRESETS[name])


def build_twin(args, errors: dict[str, float]):
    from twin.machine import Twin

    ratio = getattr(args, "stiffness_ratio", None)
    if ratio is not None and not (np.isfinite(ratio) and ratio > 0):
        raise InputError(f"stiffness ratio must be a positive number, got {ratio}", field="--stiffness-ratio")
    return Twin(errors, stiffness_ratio=ratio)


def twin_measure(args) -> int:
    from twin.campaign import THETA_LIMIT_DEG, CampaignPlan, plan_campaign, run_campaign
    from twin.tracker import LaserTracker

    geom = default_geometry()
    sigma = geom.sigma_mm if args.noise is None else args.noise
    if not np.isfinite(sigma) or sigma < 0:
        raise InputError(f"noise must be a non-negative number of mm, got {args.noise}", field="--noise")
    if args.poses < 1:
        raise InputError(f"number of poses must be at least 1, got {args.poses}", field="--poses")
    theta_max = np.rad2deg(geom.theta_max) if args.theta_max is None else args.theta_max
    if not 0 < theta_max <= THETA_LIMIT_DEG:
        raise InputError(f"tilt limit {theta_max:g} deg is outside the workspace 0..{THETA_LIMIT_DEG:g} deg "
                         "(the RSR limbs reach their stretched-link singularity near 87.5 deg)",
                         field="--theta-max")
    if args.effect:
        raise InputError("physical effects are not available yet in this version", field="--effect")
    errors = machine_errors(args)
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
        meas = run_campaign(twin, plan, LaserTracker(sigma, rng))
    except ValueError as exc:
        raise InputError(str(exc), file=args.targets, field="theta_deg" if args.targets else "--poses") from None
    source = args.errors or f"preset {args.preset or 'nominal'}"
    write_measurements(args.output, meas, comments=[
        f"pmcal twin measure: machine {geom_name()}, errors: {source}, poses {len(meas)}, "
        f"tracker sigma {sigma:g} mm, seed {args.seed}",
        "units: mm, deg; targets in the base frame O-xyz"])
    return 0


def geom_name() -> str:
    return "ocpm_2dof"


def parse_pose(text: str) -> tuple[float, float]:
    try:
        phi, theta = (float(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"expected PHI,THETA in degrees, got '{text}'", field="--pose") from None
    return phi, theta


def twin_render(args) -> int:
    from calib.ocpm.kinematics import nominal_ik
    from twin.campaign import THETA_LIMIT_DEG
    from twin.render import RenderUnavailable, render_png

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
