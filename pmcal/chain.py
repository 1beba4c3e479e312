"""The whole job on a machine described by a folder, as library functions: a virtual measurement campaign on
its twin, identification to a parameters document, targets spread over its workspace, compensation of a
target list. The command line (:mod:`pmcal.apps.chain`) is a thin layer over these.

Units: commands deg (revolute) / mm (prismatic), targets and task positions mm (base frame), angles deg.
Errors are ``{key: value}`` in each key's unit (``machine.twin.error_units``); an absent key is nominal.

Example
-------
>>> from pmcal.machines import Machine
>>> m = Machine.builtin("delta_3dof")                                  # doctest: +SKIP
>>> meas, truth = campaign(m, 48, seed=3)                               # doctest: +SKIP
>>> res = identify(m, meas)                                             # doctest: +SKIP
>>> task = sample_targets(m, 12, seed=1)                                # doctest: +SKIP
>>> commands = compensate(m, res.params, task)                          # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Mapping

import numpy as np

from pmcal import progress
from pmcal.bridge.comptable import (CONTROLLER, CORRECTION_ABS_MAX, NMOTOR_MAX, NVALUES_MAX, Axis, CompTable,
                                    Motor)
from pmcal.calib.chain_design import POOL_FACTOR, POOL_MIN, CampaignDesign, design_campaign
from pmcal.campaign_quality import chain_quality
from pmcal.calib.closed_chain import (compensate_targets, identify_chain, reading_covariance, reading_operator,
                                      structural_basis)
from pmcal.errors import InputError, RunError
from pmcal.io_chain import UNIT_SLIPS, ChainMeasurements
from pmcal.mechanism.task_space import error_families
from pmcal.twin.overconstraint import loop_summary

#: poses measured per step of the progress bar
_CHUNK = 8
#: why a campaign's poses do not assemble on the erroneous machine, and where the errors' sizes are set (the
#: motors' motion errors too: a 10 deg sigma leaves a Delta half its planned poses)
TOO_LARGE = ("its errors are too large for this workspace (the [errors] sizes in machine.toml, its [[motors]] sigma, "
             "or --errors)")


def random_errors(machine, rng: np.random.Generator) -> dict[str, float]:
    """One geometric error set of the machine's size: each error of ``machine.twin.error_keys`` drawn
    normal with the prior size ``machine.toml [errors]`` gives it (mm / deg)."""
    twin = machine.twin
    return {k: float(v) for k, v in zip(twin.error_keys, rng.normal(0.0, twin.prior_std()))}


def campaign(machine, poses: int, *, seed: int = 1, errors: str | Mapping[str, float] = "random",
             sigma_mm: float | None = None, task: np.ndarray | None = None, commands: np.ndarray | None = None,
             pose_id: list[str] | None = None, seconds_per_pose: float = 30.0,
             source: str | None = None) -> tuple[ChainMeasurements, dict[str, float]]:
    """A virtual measurement campaign on the machine's twin.

    Parameters
    ----------
    machine : :class:`pmcal.machines.Machine` (not a seeded one).
    poses : number of poses; their commands are drawn over the workspace box of machine.toml (the nominal
        machine's inverse kinematics, as a controller would), unless ``task`` is given.
    seed : seed of the errors, the commands and the tracker noise, drawn in this order (the errors are drawn
        even when ``errors`` gives them: the noise of a seed never repeats that seed's error draw, so a caller
        that drew its errors with ``random_errors(machine, default_rng(seed))`` gets noise independent of them).
    errors : ``"random"`` (:func:`random_errors`), ``"none"``, or an error set ``{key: value}``.
    sigma_mm : tracker noise, 1 sigma per coordinate, mm (default machine.toml's).
    task : (n, C) explicit targets in the machine's task coordinates instead of drawn poses.
    commands, pose_id : (n, M) explicit commands (a plan, :func:`plan`) and their ids, instead of drawn
        poses.
    seconds_per_pose : time between poses, s (the ``time_s`` column).
    source : the file ``task`` or ``commands`` came from (for messages).

    Each pose is held at its commands plus the motors' motion error (``[[motors]] sigma``, if set; the
    file records the commands). A machine measuring a distance gets scale readings: the change of the
    distance relative to the reference pose (``[tracker] reference``) plus the noise ``sigma_mm`` per reading.

    Returns
    -------
    (measurements, truth) : the measured targets (mm, base frame) and the error set measured. A pose the
    erroneous machine cannot assemble, or assembles on another branch than the nominal machine's (a target
    more than :data:`PLAUSIBLE_TARGET_MM` from the nominal one), is replaced by a further draw; one of
    explicit ``task`` or ``commands`` is left out with a warning naming it, as a real campaign skips a pose the
    machine does not reach (a :class:`RunError` when more than half are).
    """
    twin = machine.twin
    rng = np.random.default_rng(seed)
    drawn = random_errors(machine, rng)       # always drawn: the noise never repeats a seed's error draw
    if isinstance(errors, str):
        truth = drawn if errors == "random" else {}
    else:
        truth = dict(errors)
    sigma = twin.sigma_mm if sigma_mm is None else float(sigma_mm)
    explicit = task is not None or commands is not None
    if task is not None:
        commands = twin.inverse(task, None)
        bad = np.flatnonzero(~np.isfinite(commands).all(axis=1))
        if bad.size:
            raise InputError("target out of reach of the nominal machine", file=source, row=int(bad[0]) + 1,
                             field=machine.spec.task.coordinates[0])
    elif commands is None:
        commands = twin.sample_commands(poses, rng)

    motor_sigma = np.array([m.sigma for m in machine.spec.motors])
    distance = machine.spec.measure == "distance"

    def measured(cmd):
        """The rows of ``cmd`` the erroneous machine assembles on the nominal one's branch (a mask), and
        their readings (distance machines: the distances, noise-free; the readings are taken below)."""
        held = cmd + rng.normal(0.0, motor_sigma, cmd.shape) if motor_sigma.any() else cmd
        if distance:
            y = twin.observe(held, truth)
            ok = np.abs(y - twin.observe(cmd))[:, 0] <= PLAUSIBLE_TARGET_MM
        else:
            y = twin.measure(held, truth, rng, sigma)
            ok = (distance_from_nominal(machine, cmd, y) <= PLAUSIBLE_TARGET_MM).all(axis=1)
        return ok, y[ok]

    got, wanted = [], len(commands)
    with progress.progress(total=len(commands), desc="measuring", unit="pose") as bar:
        for start in range(0, len(commands), _CHUNK):
            got.append(measured(commands[start:start + _CHUNK]))
            bar.update(min(_CHUNK, wanted - start))
    kept = np.concatenate([ok for ok, _ in got])
    commands, y = commands[kept], np.concatenate([v for _, v in got])
    short = wanted - len(commands)
    def pose_ids(n: int) -> list[str]:
        return list(pose_id) if pose_id is not None else [f"P{i + 1}" for i in range(n)]

    ids = None
    if explicit:                   # the given poses: one the erroneous machine does not reach is left out
        given = pose_ids(wanted)
        ids = [i for i, k in zip(given, kept) if k]
        lost = [i for i, k in zip(given, kept) if not k]
        what = ("targets" if task is not None else "planned poses") + (f" in {source}" if source else "")
        if 2 * short > wanted:
            raise RunError(f"{short} of the {wanted} {what} cannot be assembled on the erroneous machine (on the "
                           f"nominal machine's branch): {TOO_LARGE}")
        if short:
            progress.warning(f"{short} of the {wanted} {what} cannot be assembled on the erroneous machine (on the "
                             "nominal machine's branch) and are left out, as a real campaign skips a pose the "
                             f"machine does not reach: {', '.join(lost[:8])}{' ...' if short > 8 else ''}")
        short = 0
    for _ in range(20):
        if short <= 0:
            break
        ok, more = measured(cmd := twin.sample_commands(short, rng))
        commands, y = np.concatenate([commands, cmd[ok]]), np.concatenate([y, more])
        short -= int(ok.sum())
    if short > 0:
        raise RunError(f"the erroneous machine assembles too few of the drawn poses ({short} missing): {TOO_LARGE}")
    n = len(commands)
    if ids is None:
        ids = pose_ids(n)
    readings = None
    if distance:
        D = reading_operator(n, machine.spec.reference)
        readings = np.full(n, np.nan)
        readings[1:] = D @ y[:, 0] + rng.normal(0.0, sigma, n - 1)
        y = np.zeros((n, 0, 3))
    meas = ChainMeasurements(pose_id=ids, commands=commands, targets=y,
                             time_s=np.arange(n) * float(seconds_per_pose), readings=readings, machine=machine)
    return meas, truth


def plan(machine, poses: int, seed: int = 1, sigma_mm: float | None = None) -> CampaignDesign:
    """A D-optimal identification campaign of ``poses`` poses (:func:`pmcal.calib.chain_design.design_campaign`)
    chosen from a pool drawn over the workspace of machine.toml (seed ``seed``), in driving order from the
    ``home`` keyframe."""
    twin = machine.twin
    rng = np.random.default_rng(seed)
    pool = twin.sample_commands(max(POOL_FACTOR * poses, POOL_MIN), rng)
    return design_campaign(twin, pool, poses, start=twin.home_commands, sigma_mm=sigma_mm)


#: largest plausible distance (mm) between a measured target and where the nominal machine puts it:
#: geometric errors move targets by millimetres; beyond this a unit mix-up, a mislabelled row or an
#: assembly on another branch of the chain is likelier
PLAUSIBLE_TARGET_MM = 50.0


def distance_from_nominal(machine, commands: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Distance (n, K) mm of measured ``targets`` from the nominal machine's at ``commands``; inf for a row
    the nominal chain cannot assemble, NaN for a blocked target."""
    y0 = machine.twin.targets(commands)
    d = np.linalg.norm(targets - y0, axis=2)
    d[~np.isfinite(y0).all(axis=(1, 2))] = np.inf
    return d


def check_assembles(machine, meas: ChainMeasurements, limit_mm: float = PLAUSIBLE_TARGET_MM) -> None:
    """Catch a wrong unit or a mislabelled row before identifying: every row's commands assemble the
    nominal chain, every measured target is within ``limit_mm`` of where the nominal machine puts it.
    An :class:`InputError` names file, row and field. A machine measuring a distance: every row assembles,
    and the readings are the changes of the distance the commands give, in mm (:func:`check_readings`)."""
    if machine.spec.measure == "distance":
        return check_readings(machine, meas, limit_mm)
    d = distance_from_nominal(machine, meas.commands, meas.targets)
    for i in np.flatnonzero(np.isinf(d).any(axis=1)):
        raise InputError("the nominal machine cannot assemble at these commands (wrong machine or units?)",
                         file=meas.path, row=int(i) + 1, field=machine.spec.motor_columns[0])
    bad = np.argwhere(d > limit_mm)
    if bad.size:
        i, k = (int(v) for v in bad[0])
        y = meas.targets[i, k]
        scale = np.linalg.norm(y) / max(np.linalg.norm(y) + d[i, k], 1e-9)
        hint = " (values look like metres: the file must be in mm)" if scale < 2e-3 else ""
        slips = np.array([UNIT_SLIPS[m.unit][0] for m in machine.spec.motors])
        if not hint and np.all(distance_from_nominal(machine, meas.commands[i:i + 1] * slips,
                                                     meas.targets[i:i + 1]) <= limit_mm):
            hint = " (the commands look like radians or metres: the file must be in degrees and mm)"
        raise InputError(f"target t{k + 1} is {d[i, k]:.4g} mm from where the nominal machine puts it (limit "
                         f"{limit_mm:g} mm){hint}", file=meas.path, row=i + 1, field=f"t{k + 1}_x")


#: accepted least-squares ratio of scale readings to the nominal machine's distance changes (geometric errors
#: change them by a few per cent; metres or micrometres by 1000)
PLAUSIBLE_READING_RATIO = (0.5, 2.0)


def check_readings(machine, meas: ChainMeasurements, limit_mm: float = PLAUSIBLE_TARGET_MM) -> None:
    """A distance machine's measurement file against its nominal twin: every row assembles, the readings
    follow the distance changes the commands give (their least-squares ratio within
    :data:`PLAUSIBLE_READING_RATIO`: a unit mix-up moves it by 1000) and none is more than ``limit_mm``
    from the nominal change."""
    d0 = machine.twin.observe(meas.commands)[:, 0]
    field = machine.spec.motor_columns[0]
    for i in np.flatnonzero(~np.isfinite(d0)):
        raise InputError("the nominal machine cannot assemble at these commands (wrong machine or units?)",
                         file=meas.path, row=int(i) + 1, field=field)
    rows = np.flatnonzero(~meas.chain_starts())
    expected = reading_operator(len(meas), machine.spec.reference, meas.chain) @ d0
    got = meas.reading_rows()
    scale = float(expected @ expected)
    if scale >= 1.0:                              # under 1 mm of change the ratio says nothing
        ratio = float(got @ expected) / scale
        lo, hi = PLAUSIBLE_READING_RATIO
        if not lo <= ratio <= hi:
            hint = " (metres?)" if abs(ratio) < 0.01 else " (micrometres?)" if abs(ratio) > 100 else ""
            raise InputError(f"the readings are {ratio:.3g} times the distance changes the commands give: they "
                             f"must be in mm{hint}", file=meas.path, row=int(rows[np.argmax(np.abs(expected))]) + 1,
                             field="reading_mm")
    off = np.abs(got - expected)
    if off.size and off.max() > limit_mm:
        k = int(np.argmax(off))
        raise InputError(f"reading {got[k]:.4g} mm is {off[k]:.4g} mm from the change the nominal machine gives "
                         f"(limit {limit_mm:g} mm)", file=meas.path, row=int(rows[k]) + 1, field="reading_mm")


def identify(machine, meas: ChainMeasurements, sigma_mm: float | None = None, basis=None):
    """Identify the machine's geometric errors from a measurement campaign: the base set the campaign
    determines, by Levenberg-Marquardt with the Tikhonov prior of machine.toml (a distance machine whose
    motors have a motion error ``sigma``: generalised least squares with :func:`reading_covariance`)
    (:func:`pmcal.calib.closed_chain.identify_chain`). Checks first that the file is plausible for the
    machine (:func:`check_assembles`). ``basis``: the base set to identify (:func:`reference_basis`, the same
    for every campaign); None: the campaign's own. Returns the :class:`~pmcal.calib.closed_chain.ChainIdentResult`."""
    check_assembles(machine, meas)
    try:
        if machine.spec.measure == "distance":
            motor_sigma = [m.sigma for m in machine.spec.motors]
            cov = reading_covariance(machine.twin, meas.commands, motor_sigma, sigma_mm, meas.chain) \
                if any(motor_sigma) and machine.spec.errors.motor_zero else None
            return identify_chain(machine.twin, meas.commands, meas.reading_rows(), sigma_mm, segments=meas.chain,
                                  covariance=cov, basis=basis)
        return identify_chain(machine.twin, meas.commands, meas.targets, sigma_mm, basis=basis)
    except ValueError as exc:            # too few poses for the base set, poses the machine cannot assemble
        raise InputError(str(exc), file=meas.path) from None
    except np.linalg.LinAlgError:        # the fit blew up: name the row farthest from the nominal machine
        raise InputError(_blow_up(machine, meas), file=meas.path) from None


def _blow_up(machine, meas: ChainMeasurements) -> str:
    """What to say when the fit itself failed: the row whose targets are farthest from the nominal machine,
    if it stands out of the others (a gross outlier), else that the data do not fit the machine."""
    if machine.spec.measure != "distance":
        d = np.nanmax(np.where(np.isfinite(d := distance_from_nominal(machine, meas.commands, meas.targets)), d, -1),
                      axis=1)
        i = int(np.argmax(d))
        rest = np.delete(d, i)
        if rest.size and d[i] > 3 * max(float(np.max(rest)), 0.1):
            return (f"the fit failed; row {i + 1} ({meas.pose_id[i]}) is {d[i]:.3g} mm from where the nominal machine "
                    f"puts its targets, the other rows at most {np.max(rest):.3g} mm: a gross outlier (remeasure or "
                    "delete the row)")
    return ("the fit failed (the linear algebra did not converge): the measurements do not fit this machine; check "
            "the rows, the units and --machine")


#: A target (or reading) this many sigma off the fit of the other poses is a gross outlier
OUTLIER_SIGMA = 10.0
#: Rows :func:`gross_outliers` takes out at most: more are not a few bad rows but a model that does not fit
OUTLIER_ROWS_MAX = 3


def distinct_poses(meas: ChainMeasurements, resolution: float = 1e-6) -> int:
    """How many different command rows ``meas`` holds (deg / mm, equal to ``resolution``)."""
    return len(np.unique(np.round(np.asarray(meas.commands, float) / resolution), axis=0))


def subset(meas: ChainMeasurements, keep: np.ndarray) -> ChainMeasurements:
    """The rows ``keep`` (boolean mask) of a measurement set of targets (not of distance readings)."""
    pick = lambda a: None if a is None else np.asarray(a)[keep]           # noqa: E731
    return dataclasses.replace(meas, pose_id=[p for p, k in zip(meas.pose_id, keep) if k], commands=meas.commands[keep],
                               targets=meas.targets[keep], time_s=pick(meas.time_s), temp_c=pick(meas.temp_c))


def gross_outliers(machine, meas: ChainMeasurements, res, sigma_mm: float | None = None, basis=None,
                   chi2_limit: float = 2.0) -> list[str]:
    """Rows of a campaign that are gross outliers: when the fit ``res`` leaves chi2/dof above ``chi2_limit``,
    the row whose target is farthest off is taken out and the rest identified again, at most
    :data:`OUTLIER_ROWS_MAX` times; if the others then fit (chi2/dof at most ``chi2_limit``), each row taken
    out whose target is more than :data:`OUTLIER_SIGMA` sigma off that fit is named (row counted from 1,
    pose id, target, mm and sigma). Empty otherwise, and for a machine measuring a distance (its readings
    are differences of neighbouring rows)."""
    if machine.spec.measure == "distance" or res.chi2_per_dof <= chi2_limit or len(meas) < 3:
        return []
    sigma = float(res.sigma_mm if sigma_mm is None else sigma_mm)
    keep = np.ones(len(meas), bool)
    fit = res
    for _ in range(OUTLIER_ROWS_MAX):
        d = residuals(machine, fit.params, meas)
        worst = np.where(keep, np.nanmax(np.where(np.isfinite(d), d, -np.inf), axis=1), -np.inf)
        keep[int(np.argmax(worst))] = False
        try:
            fit = identify(machine, subset(meas, keep), sigma_mm, basis)
        except InputError:                       # the rest no longer determine the base set
            return []
        if fit.chi2_per_dof <= chi2_limit:
            break
    else:
        return []
    d = residuals(machine, fit.params, meas)
    out = []
    for i in np.flatnonzero(~keep):
        k = int(np.nanargmax(d[i]))
        if d[i, k] > OUTLIER_SIGMA * sigma:
            out.append(f"row {i + 1} ({meas.pose_id[i]}): target t{k + 1} is {d[i, k]:.3g} mm "
                       f"({d[i, k] / sigma:.0f} sigma) off the fit of the other poses")
    return out


def campaign_quality(machine, meas: ChainMeasurements, res, sigma_mm: float | None = None,
                     reference=None) -> dict:
    """The ``quality`` object of an identification (:func:`pmcal.campaign_quality.chain_quality`): the
    campaign's rank against the machine's structural base set (``reference``, made by :func:`reference_basis`
    when not given), its distinct poses, its gross outliers (:func:`gross_outliers`), whether the fit reaches
    the noise floor and predicts the poses it did not fit (``res.info["held_out"]``)."""
    reference = reference_basis(machine) if reference is None else reference
    per_pose = 1 if machine.spec.measure == "distance" else 3 * len(machine.spec.targets)
    outliers = gross_outliers(machine, meas, res, sigma_mm, basis=None)
    fit = {"chi2": float(res.chi2), "dof": float(res.dof), "residual_rms_mm": float(res.residual_rms_mm),
           "sigma_mm": float(res.sigma_mm), "held_out": res.info.get("held_out")}
    return chain_quality(int(res.rank), int(reference.rank), len(meas), distinct_poses(meas), per_pose, outliers,
                         fit, required_rank=reference.clear_rank())


#: poses of the reference campaign of :func:`reference_basis` (at least; more for a machine with many errors)
REFERENCE_POSES = 48


def reference_basis(machine):
    """The machine's structural base set (:func:`pmcal.calib.closed_chain.structural_basis`) at a reference
    campaign that depends on the machine alone: commands drawn over its workspace from a fixed seed (0),
    enough poses for three readings per error. Two identifications of the machine are compared in it."""
    twin = type(machine.twin)(machine.spec)        # a fresh twin: no warm start of this session's solves
    per_pose = 1 if machine.spec.measure == "distance" else 3 * len(machine.spec.targets)
    poses = max(REFERENCE_POSES, -(-3 * len(twin.error_keys) // per_pose))
    return structural_basis(twin, twin.sample_commands(poses, np.random.default_rng(0)))


#: an error whose posterior standard deviation stays above this fraction of its prior one is not seen by the
#: campaign's readings (:func:`unseen_task_errors`)
UNSEEN_FRACTION = 0.95
#: an unseen error matters when, at its prior size, it moves the task point by more than the tracker noise
#: (position) or than the noise over this lever arm (orientation), mm
UNSEEN_ARM_MM = 100.0


def _prior_set_json(dirs: dict | None) -> dict | None:
    """``info["prior_set"]`` for the JSON: ``poses_needed`` null where no number of poses would do."""
    if dirs is None:
        return None
    need = dirs["poses_needed"]
    return {"count": int(dirs["count"]), "poses_needed": int(need) if np.isfinite(need) else None}


def unseen_task_errors(machine, result, poses: int = 8) -> list[str]:
    """Errors that move the task point but that the campaign's readings do not see: the data leave them at
    their prior (:attr:`~pmcal.calib.closed_chain.ChainIdentResult.error_covariance`), so no compensation
    corrects them (a task site on a body no tracker nest sits on, e.g. a CAD export's end-effector frame).
    Named when, at their prior size and somewhere among ``poses`` commands drawn over the workspace, they
    move the task point by more than the tracker noise and no reading by more than the noise (a reading
    relative to a reference pose: its change from the first pose). An error the readings see only in a
    combination with others (a coupler's offset beside a motor zero) also stays at its prior, but the
    combination is identified and the task sees the same one: it is not named. Empty without a prior."""
    if result.error_covariance is None:
        return []
    keys = list(result.params)
    twin = machine.twin
    prior = twin.prior_std(keys)
    blind = np.sqrt(np.clip(np.diag(result.error_covariance), 0.0, None)) > UNSEEN_FRACTION * prior
    if not blind.any():
        return []
    commands = twin.sample_commands(poses, np.random.default_rng(0))
    J = twin.task_jacobian(commands, result.params, keys)
    coords = machine.spec.task.coordinates
    limit = np.array([result.sigma_mm if c.endswith("_mm") else np.rad2deg(result.sigma_mm / UNSEEN_ARM_MM)
                      for c in coords])
    moved = (np.nanmax(np.abs(J) * prior, axis=0) > limit[:, None]).any(axis=0)
    O = twin.observation_jacobian(commands, result.params, keys)               # (N, R, P) mm per key unit
    if twin.reading_reference is not None:
        O = O - O[:1]
    seen = np.nanmax(np.abs(O) * prior, axis=(0, 1)) > result.sigma_mm
    return [k for k, b, m, v in zip(keys, blind, moved, seen) if b and m and not v]


#: share of the predicted task variance one posterior direction must carry to be named, and how many tracker
#: sigmas (over the whole campaign) a prior-sized move of it may show at most: below 1 the readings barely see it
DOMINANT_SHARE, DOMINANT_SEEN_SIGMA = 0.5, 1.0


def dominant_task_uncertainty(machine, result, n_poses: int, samples: int = 8) -> dict | None:
    """The combination of errors that carries most of the predicted task error, when the campaign barely sees
    it: ``{share, std, total, unit, seen_sigma, poses, poses_to_halve, errors, suggested_nest}`` or None.

    The posterior over every error (:attr:`~pmcal.calib.closed_chain.ChainIdentResult.error_covariance`),
    whitened by the prior sizes, propagated to the task's first family (position mm, else orientation deg)
    over ``samples`` commands drawn over the workspace: its eigen-directions split the predicted task variance.
    The largest is named when it carries at least :data:`DOMINANT_SHARE` of it and the campaign sees a
    prior-sized move of it at less than :data:`DOMINANT_SEEN_SIGMA` tracker sigma (``seen_sigma``, from its
    posterior variance ``1 / (1 + I)``, over the campaign's ``n_poses`` poses, ``poses``). ``std`` its task
    RMS of ``total``; ``poses_to_halve`` how many poses of the same kind halve it (``n_poses (3 + 4 I) / I``);
    ``errors`` its four largest components (key, weight per prior size). gepetto_delta (tests/corpus): the nests
    and the task point on one body, a rotation about the line through the two nests: 92 % of 0.019 mm, seen at
    0.26 sigma, about 2300 poses to halve. ``suggested_nest``: where one more tracker nest would see it
    (:func:`suggest_nest`; gepetto_delta: 4 mm off the nests' line on the effector, 0.018 -> 0.0024 mm). None
    without a prior (or a finite posterior) or when no direction dominates so."""
    if result.error_covariance is None or not np.isfinite(result.error_covariance).all():
        return None
    keys = list(result.params)
    twin = machine.twin
    size = twin.prior_std(keys)
    coords = machine.spec.task.coordinates
    _, unit, members, _ = error_families(coords)[0]
    idx = [i for i, c in enumerate(coords) if c in members]
    commands = twin.sample_commands(samples, np.random.default_rng(0))
    J = np.nan_to_num(twin.task_jacobian(commands, result.params, keys)[:, idx, :]).reshape(-1, len(keys)) * size
    post = result.error_covariance / np.outer(size, size)                  # posterior in prior sizes
    ev, vecs = np.linalg.eigh(post)
    R = vecs * np.sqrt(np.clip(ev, 0.0, None))                              # post = R R'
    w, V = np.linalg.eigh(R.T @ (J.T @ J / len(commands)) @ R)
    k = int(np.argmax(w))
    if w.sum() <= 0 or w[k] < DOMINANT_SHARE * w.sum():
        return None
    d = R @ V[:, k]
    u = d / np.linalg.norm(d)
    info = max(1.0 / float(u @ post @ u) - 1.0, 0.0)
    if info >= DOMINANT_SEEN_SIGMA ** 2:
        return None
    top = np.argsort(-np.abs(u))[:4]
    return {"share": float(w[k] / w.sum()), "std": float(np.sqrt(w[k])), "total": float(np.sqrt(w.sum())),
            "unit": unit, "seen_sigma": float(np.sqrt(info)), "poses": int(n_poses),
            "poses_to_halve": float(n_poses * (3.0 + 4.0 * info) / info) if info > 0 else None,
            "errors": {keys[i]: float(u[i]) for i in top},
            "suggested_nest": suggest_nest(machine, result, commands, J, post, u, n_poses)}


#: candidate nest positions per body axis (a grid over the bounding box of the body's geoms)
NEST_GRID = 5


def suggest_nest(machine, result, commands, J_task, post, u, n_poses: int) -> dict | None:
    """Where one more tracker nest would see the barely seen combination ``u`` (prior-size units) of
    :func:`dominant_task_uncertainty` best: ``{body, position_mm, seen_sigma, total}`` or None.

    Candidates: a :data:`NEST_GRID` ^3 grid over the bounding box of the geoms of each body that carries a
    tracker nest or the task site (body frame, mm). Each candidate's readings over ``commands`` (exact
    derivatives of a point fixed on the body, :meth:`~pmcal.twin.closed_chain.ClosedChainTwin.body_point_jacobian`)
    are added to the posterior ``post`` (prior-size units) as ``n_poses`` poses of that kind would add them;
    the one that leaves the smallest predicted task error (``J_task``: the task's first family per prior size,
    rows over ``commands``) is returned with that error (``total``, the family's unit, RMS) and how many
    tracker sigma the campaign would then see a prior-sized move of ``u`` at (``seen_sigma``). None for a
    distance reading (no nest to add)."""
    twin = machine.twin
    if machine.spec.measure == "distance":
        return None
    keys = list(result.params)
    size = twin.prior_std(keys)
    model = twin.model
    bodies = [b for b in dict.fromkeys(int(model.site_bodyid[s]) for s in [*twin.target_sites, twin.task_site])
              if b != 0]                                                   # a nest on the world sees nothing
    scale = n_poses / len(commands) / result.sigma_mm ** 2
    best = None
    for body in bodies:
        lo, hi = twin.body_bounds_mm(body)
        grid = np.array(list(itertools.product(*[np.linspace(a, b, NEST_GRID) for a, b in zip(lo, hi)])))
        Jp = np.nan_to_num(twin.body_point_jacobian(commands, body, grid, result.params, keys)) * size
        for q, p in enumerate(grid):
            A = Jp[:, q].reshape(-1, len(keys))                           # its readings' rows (Woodbury update)
            K = A @ post
            new = post - K.T @ np.linalg.solve(np.eye(len(A)) / scale + K @ A.T, K)
            total = float(np.sqrt(max(np.einsum("ij,jk,ik->", J_task, new, J_task), 0.0) / len(commands)))
            if best is None or total < best["total"]:
                seen = max(1.0 / float(u @ new @ u) - 1.0, 0.0)
                best = {"body": model.body(body).name, "position_mm": [round(float(v), 1) for v in p],
                        "seen_sigma": float(np.sqrt(seen)), "total": total}
    return best


def dominant_line(d: dict | None, unseen=()) -> str | None:
    """The warning for a barely seen combination of errors that carries the predicted task error
    (:func:`dominant_task_uncertainty`), or None: none, or its errors already named as ``unseen`` by the
    tracker (:func:`unseen_task_errors`, said once)."""
    if not d or set(d["errors"]) & set(unseen):
        return None
    parts = ", ".join(f"{k} {v:+.2f}" for k, v in d["errors"].items())
    halve = f"about {d['poses_to_halve']:.0f}" if d["poses_to_halve"] else "no number of poses"
    line = (f"one combination of errors carries {100 * d['share']:.0f} % of the predicted task error "
            f"({d['std']:.2g} of {d['total']:.2g} {d['unit']} RMS; {parts}, per [errors] size) and the {d['poses']} "
            f"poses see it at {d['seen_sigma']:.2f} tracker sigma: more poses like them gain slowly ({halve} to "
            "halve it); a tracker target nearer the task point, or off the line or plane of the present ones, "
            "would see it")
    nest = d.get("suggested_nest")
    if nest:
        x, y, z = nest["position_mm"]
        where = (f"at ({x:g}, {y:g}, {z:g}) mm in body '{nest['body']}' would see it at {nest['seen_sigma']:.1f} "
                 f"tracker sigma, predicted task error {nest['total']:.2g} {d['unit']} RMS")
        line += (f": one more nest {where}" if nest["seen_sigma"] >= DOMINANT_SEEN_SIGMA else
                 f"; no one nest on the bodies that carry the nests or the task site sees it well (the best, {where})")
    return line


def params_document(machine, result, source: str | None = None) -> dict:
    """The parameters JSON of an identification (docs/formats.md, "Any machine"): ``params`` every error
    considered (mm / deg; the identified machine: each base value spread over the errors it regroups,
    :func:`pmcal.calib.closed_chain.spread_map`), ``units``, the base parameters (``identifiable``), their
    identified ``values``, their ``uncertainty`` (1 sigma, posterior), ``covariance`` (posterior, in
    the order of ``identifiable``), ``prior_covariance`` (the ``[errors]`` prior carried onto the base
    parameters, same order) and ``crlb`` (data alone), what each base value
    estimates (``combinations``), what the data cannot see (``unidentifiable``), ``weak`` ones, fit
    quality; ``unseen_by_tracker``: errors that move the task point but no reading (:func:`unseen_task_errors`);
    ``dominant_task_uncertainty`` (:func:`dominant_task_uncertainty`)."""
    units = dict(zip(machine.twin.error_keys, machine.twin.error_units()))
    return {
        "mechanism": machine.name, "model": "closed_chain", "method": "lm+tikhonov",
        "units": {k: units[k] for k in result.params},
        "params": {k: float(v) for k, v in result.params.items()},
        "identifiable": list(result.base), "values": {k: float(v) for k, v in zip(result.base, result.x)},
        "uncertainty": dict(result.std),
        "covariance": np.asarray(result.covariance, float).tolist(), "crlb": dict(result.crlb),
        "prior_covariance": np.asarray(result.info["prior_covariance"], float).tolist(),
        "combinations": dict(result.combinations), "unidentifiable": list(result.unidentifiable),
        "weak": list(result.weak), "prior_set": _prior_set_json(result.info.get("prior_set")),
        "rank": int(result.rank), "n_errors": len(result.params),
        "condition_number": float(result.condition_number), "chi2_per_dof": float(result.chi2_per_dof),
        "residual_rms_mm": float(result.residual_rms_mm), "sigma_mm": float(result.sigma_mm),
        "n_poses": int(result.n_poses), "source": source, "success": bool(result.success),
        "loops": loop_summary(machine.twin), "held_out": dict(result.info["held_out"]),
        "beyond_prior": list(result.info["beyond_prior"]),
        "unseen_by_tracker": unseen_task_errors(machine, result),
        "dominant_task_uncertainty": dominant_task_uncertainty(machine, result, int(result.n_poses)),
        "message": result.message,
    }


def residuals(machine, params: Mapping[str, float] | None, meas: ChainMeasurements) -> np.ndarray:
    """Distance (n, K) mm between each measured target and where the machine with errors ``params`` puts it
    at the row's commands (NaN for a blocked target or a row it cannot assemble); for a machine measuring a
    distance, (n, 1) the reading minus the change that machine gives (NaN on the first pose of a chain)."""
    if machine.spec.measure == "distance":
        out = np.full((len(meas), 1), np.nan)
        D = reading_operator(len(meas), machine.spec.reference, meas.chain)
        out[~meas.chain_starts(), 0] = meas.reading_rows() - D @ machine.twin.observe(meas.commands, params)[:, 0]
        return out
    return np.linalg.norm(meas.targets - machine.twin.targets(meas.commands, params), axis=2)


def sample_targets(machine, count: int, seed: int = 1) -> np.ndarray:
    """``count`` targets (count, C) in the machine's task coordinates, drawn uniformly over the workspace
    box of machine.toml and kept where the nominal machine reaches them within its motor ranges."""
    twin = machine.twin
    rng = np.random.default_rng(seed)
    commands = twin.sample_commands(count, rng)
    return twin.forward(commands)


def compensate(machine, params: Mapping[str, float], task: np.ndarray, path: str | None = None) -> np.ndarray:
    """Motor commands (n, M) that put the task site of the machine with errors ``params`` at ``task`` (n, C):
    its inverse kinematics with the identified errors. A target it cannot reach is an :class:`InputError`
    naming the row of ``path`` and the reason."""
    commands = compensate_targets(machine.twin, dict(params), task)
    for i in np.flatnonzero(~np.isfinite(commands).all(axis=1)):
        _, why = machine.twin.inverse_report(task[i:i + 1], dict(params))
        raise InputError(f"not reachable by the identified machine: {why[0]}", file=path, row=int(i) + 1,
                         field=machine.spec.task.coordinates[0])
    return commands


#: most axes and motors a compensation table holds (the PLC's arrays, docs/compensation_table.md)
TABLE_AXES_MAX = 3


def table_refusal(machine) -> str | None:
    """Why ``machine`` gets no compensation table (one line, with what it gets instead), or None."""
    axes, coords = machine.spec.table_axes, machine.spec.task.coordinates
    if len(coords) > TABLE_AXES_MAX:
        why = (f"its {len(coords)} task coordinates ({', '.join(coords)}) are more than a compensation table "
               f"holds ({TABLE_AXES_MAX} axes at most)")
    elif len(machine.spec.motors) > NMOTOR_MAX:
        why = f"its {len(machine.spec.motors)} motors are more than a table holds ({NMOTOR_MAX} at most)"
    elif not axes:
        why = "machine.toml names no [table] axes"
    elif len(axes) < len(coords):
        why = f"the [table] axes ({', '.join(axes)}) cover {len(axes)} of its {len(coords)} task coordinates"
    else:
        return None
    return (f"no compensation table for machine {machine.name}: {why}; this machine gets offline compensation "
            f"of target lists: compensate PARAMS.json --targets TARGETS.csv -o SETPOINTS.csv")


#: a default table box keeps the nominal commands at its nodes this fraction of each motor's range away from
#: the range's ends (room for the calibration's corrections)
TABLE_RANGE_MARGIN = 0.02
#: the default correction bound: this many standard deviations of the largest correction that random errors of
#: machine.toml's sizes call for (linearised at the table's nodes), and at least the fixed default
CORRECTION_SIGMAS = 5.0
#: nodes at most at which the default correction bound is evaluated (evenly spread through the grid)
CORRECTION_NODES = 125


def _grid_points(box: Mapping[str, tuple[float, float]], axes, nodes) -> np.ndarray:
    """The nodes (N, axes) of a grid over ``box`` (axis -> (lo, hi)), ``nodes`` per axis, first axis slowest."""
    lines = [np.linspace(*box[a], n) for a, n in zip(axes, nodes)]
    return np.stack([g.ravel() for g in np.meshgrid(*lines, indexing="ij")], axis=1)


def table_box(machine, nodes) -> dict[str, tuple[float, float]]:
    """The span of each ``[table]`` axis: machine.toml's where it gives one; for the others (the default) the
    workspace box shrunk about its centre by the largest factor (bisection, to 1 %) at which the nominal
    machine reaches every node of the grid with its commands inside the motor ranges less
    :data:`TABLE_RANGE_MARGIN` (a real machine does not reach the workspace box's corners). InputError naming
    machine.toml when not even a small box about the centre is reachable."""
    spec = machine.spec
    grid = spec.table
    box = {a: tuple(grid.box[a]) for a in spec.table_axes}
    if not grid.box_default:
        return box
    order = [spec.table_axes.index(c) for c in spec.task.coordinates]
    rng = np.array([m.range for m in spec.motors], float)
    lo, hi = rng[:, 0] + TABLE_RANGE_MARGIN * np.ptp(rng, axis=1), rng[:, 1] - TABLE_RANGE_MARGIN * np.ptp(rng, axis=1)

    def scaled(f: float) -> dict[str, tuple[float, float]]:
        out = dict(box)
        for a in grid.box_default:
            c, h = (box[a][0] + box[a][1]) / 2, (box[a][1] - box[a][0]) / 2
            out[a] = (c - f * h, c + f * h)
        return out

    def reached(f: float) -> bool:
        task = _grid_points(scaled(f), spec.table_axes, nodes)[:, order]
        cmd = machine.twin.inverse(task, None)
        return bool(np.all(np.isfinite(cmd)) and np.all((cmd >= lo) & (cmd <= hi)))

    if reached(1.0):
        return box
    progress.status("compensation table: the workspace box's corners are out of reach; finding the largest "
                    "reachable box about its centre")
    good, bad = 0.0, 1.0
    while bad - good > 0.01:
        mid = (good + bad) / 2
        good, bad = (mid, bad) if reached(mid) else (good, mid)
    if good == 0.0:
        raise InputError(f"no table box about the workspace's centre is reachable by the nominal machine with its "
                         f"commands inside the motor ranges; give the table's span ({', '.join(grid.box_default)}"
                         f" = [lo, hi]) in [table]", file=str(spec.folder / "machine.toml"), field="table")
    return scaled(good)


def correction_bound(machine, nominal_commands: np.ndarray) -> float:
    """The largest correction a table accepts (deg or mm, every motor): ``[table] max_correction`` when
    machine.toml gives it; by default :data:`CORRECTION_SIGMAS` standard deviations of the correction that
    random errors of the ``[errors]`` sizes call for, at most :data:`CORRECTION_NODES` of the nodes
    (commands ``nominal_commands`` (N, M)), linearised: ``dm = -(dy/dm)^+ dy/dp p`` with ``dy/dm`` the task's
    derivative by the motor zero offsets (which move a joint as its command does); at least the fixed default
    and at most the PLC's ``CORRECTION_ABS_MAX``. Without motor zero offsets among the errors: the fixed
    default."""
    grid, twin = machine.spec.table, machine.twin
    zeros = [f"{m.name}.dzero" for m in machine.spec.motors]
    if not grid.max_correction_default or not set(zeros) <= set(twin.error_keys):
        return grid.max_correction
    pick = np.unique(np.linspace(0, len(nominal_commands) - 1, CORRECTION_NODES).astype(int))
    cmd = nominal_commands[pick]
    Jm = twin.task_jacobian(cmd, None, zeros)                               # (n, C, M) per motor unit
    Jp = twin.task_jacobian(cmd, None) * twin.prior_std()                   # (n, C, P) per prior sigma
    sigma = np.sqrt(np.sum((np.linalg.pinv(Jm) @ Jp) ** 2, axis=-1))        # (n, M)
    return float(min(CORRECTION_ABS_MAX, max(grid.max_correction, CORRECTION_SIGMAS * np.nanmax(sigma))))


def _probe_box(machine, params: Mapping[str, float], axes, order: list[int], motors) -> None:
    """Before the grid: the table box's corners and centre (2**d + 1 points) reachable by the identified
    machine within its motor ranges, else an :class:`InputError` naming the corner at once (a box beyond the
    reach otherwise costs the inverse kinematics of every node first)."""
    corners = np.array(list(itertools.product(*[(a.min, a.max) for a in axes])), float)
    probe = np.vstack([corners, corners.mean(axis=0)])[:, order]
    commands = compensate_targets(machine.twin, dict(params), probe)
    lo = np.array([m.min for m in motors])
    hi = np.array([m.max for m in motors])
    ok = np.isfinite(commands).all(axis=1) & np.all((commands >= lo) & (commands <= hi), axis=1)
    for i in np.flatnonzero(~ok)[:1]:
        where = ", ".join(f"{c}={v:g}" for c, v in zip(machine.spec.task.coordinates, probe[i]))
        what = "centre" if i == len(probe) - 1 else "corner"
        raise InputError(f"the table box's {what} {where} is not reachable by the identified machine within its "
                         "motor ranges: shrink the table box ([table] box, else [workspace])",
                         file=str(machine.spec.folder / "machine.toml"), field="table")


def compensation_table(machine, params: Mapping[str, float], version: int, nodes=None, absolute: bool | None = None):
    """The compensation table (format 4) of a machine folder: a grid over its ``[table]`` axes (``[table]
    nodes`` per axis, or ``nodes``; the box of ``[table]`` or the workspace).

    By default (``[table] reference = "controller"``) the table holds, at each node, the correction to add
    to the motion controller's own nominal inverse kinematics: ``m_calibrated - m_nominal`` (deg or mm),
    with ``m_calibrated`` the identified machine's IK (:func:`compensate_targets`) and ``m_nominal`` the
    nominal MJCF twin's (``machine.twin.inverse(task, None)``), header ``nReference = 2``; the motors'
    ``min``/``max`` are then ``-+[table] max_correction`` and ``max_step`` is ``[table]
    max_correction_step``. With ``absolute`` (or ``[table] reference = "none"``) it holds the absolute
    commands (``nReference = 0``). Either way the absolute commands are checked first: a node the
    identified machine cannot reach, or reaches only outside a motor's range (``[[motors]] range``), is an
    :class:`InputError` naming the node (its CSV row); so is, for absolute commands, a step above ``[table]
    max_step`` between neighbours (corrections do not interpolate the commands: their steps do not
    matter), and for corrections a node the nominal machine cannot reach, and a correction or correction
    step above its bound. Validated."""
    why = table_refusal(machine)
    if why:
        raise InputError(why, field="--table")
    spec = machine.spec
    grid = spec.table
    toml = str(spec.folder / "machine.toml")
    where = {"field": "--grid"} if nodes else {"file": toml, "field": "table.nodes"}   # who chose the nodes
    nodes = tuple(int(n) for n in (nodes or grid.nodes))
    if len(nodes) != len(spec.table_axes) or min(nodes) < 2:
        raise InputError(f"expected {len(spec.table_axes)} node counts >= 2 (one per table axis "
                         f"{', '.join(spec.table_axes)}), got {','.join(map(str, nodes))}", **where)
    values = int(np.prod(nodes, dtype=object)) * len(spec.motors)        # before anything is built
    if values > NVALUES_MAX:
        raise InputError(f"grid {'x'.join(map(str, nodes))} x {len(spec.motors)} motors = {values} values, more than "
                         f"the PLC's {NVALUES_MAX}: fewer nodes per axis", **where)
    box = table_box(machine, nodes)
    axes = [Axis.of_column(a, *box[a], n) for a, n in zip(spec.table_axes, nodes)]
    motors = [Motor(m.name, m.unit, m.range[0], m.range[1], grid.max_step) for m in spec.motors]
    order = [spec.table_axes.index(c) for c in spec.task.coordinates]
    coords = spec.task.coordinates

    def fill(points: np.ndarray) -> np.ndarray:
        task = points[:, order]
        progress.status(f"compensation table: inverse kinematics at {len(task)} nodes")
        commands = compensate_targets(machine.twin, dict(params), task)
        lo = np.array([m.min for m in motors])
        hi = np.array([m.max for m in motors])
        ok = np.isfinite(commands).all(axis=1) & np.all((commands >= lo) & (commands <= hi), axis=1)
        for i in np.flatnonzero(~ok)[:1]:
            where = ", ".join(f"{c}={v:g}" for c, v in zip(coords, task[i]))
            raise InputError(f"table node {int(i) + 1} ({where}) is not reachable by the identified machine within "
                             "its motor ranges; shrink the table box", file=toml, field="table")
        return commands

    _probe_box(machine, params, axes, order, motors)
    table = CompTable.from_grid(fill, machine=spec.name, version=int(version), axes=axes, motors=motors)
    absolute = bool(absolute) or (absolute is None and grid.reference == "none")
    defect = table.defect()
    if defect is not None and (absolute or defect.kind != "step"):
        table.validate()                      # names the node; a correction table's commands need no max_step
    if absolute:
        return table
    if grid.max_correction > CORRECTION_ABS_MAX:
        raise InputError(f"{grid.max_correction:g} is more than the PLC accepts (GVL_CompTableParam."
                         f"CORRECTION_ABS_MAX {CORRECTION_ABS_MAX:g})", file=str(spec.folder / "machine.toml"),
                         field="table.max_correction")

    def nominal(points: np.ndarray) -> np.ndarray:
        task = points[:, order]
        commands = machine.twin.inverse(task, None)
        for i in np.flatnonzero(~np.isfinite(commands).all(axis=1))[:1]:
            where = ", ".join(f"{c}={v:g}" for c, v in zip(coords, task[i]))
            raise InputError(f"table node {int(i) + 1} ({where}) is not reachable by the nominal machine (the "
                             "controller's inverse kinematics): no correction to it; shrink the table box",
                             file=toml, field="table")
        return commands

    m_nominal = nominal(table.nodes().reshape(-1, len(axes)))
    c, step = correction_bound(machine, m_nominal), grid.max_correction_step
    bounds = [Motor(m.name, m.unit, -c, c, step) for m in motors]
    corrections = CompTable(machine=spec.name, version=int(version), axes=table.axes, motors=bounds,
                            values=table.values - m_nominal.reshape(table.values.shape), reference=CONTROLLER)
    try:
        return corrections.validate()
    except InputError as exc:
        raise InputError(f"{exc.message}{'' if exc.row is None else f' (table node {exc.row})'}; the calibration "
                         f"moves this node further than [table] max_correction {c:g} / max_correction_step "
                         f"{step:g} allow: check the calibration, or raise them", file=toml,
                         field="table") from None
