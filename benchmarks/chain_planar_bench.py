"""The seeded planar_2dof on the generic closed-chain core vs its dedicated code, same data.

The generic path is ``mjcf/planar_2dof/chain`` (the MJCF described as data: a ``"distance"`` measurement
between O1 and O2 read relative to the previous position, the paper's error names mapped onto frame
displacements by ``[names]``) run through the generic algorithms of :mod:`pmcal.calib.closed_chain`
(``identify_chain``, ``reading_covariance``, ``compensate_targets``) on two implementations of the same
forward-model protocol: the closed-form fast path :class:`pmcal.mechanism.planar.chain.PlanarChainModel`
(the paper's eq. 1-13 with exact derivatives at the real configuration) and, for reference, the MuJoCo
twin ``NamedModel(ClosedChainTwin(spec), spec.names)`` (Newton on the loop closures, IFT derivatives).
The dedicated path is :mod:`pmcal.calib.planar.identification` (the paper's linearised model, eq. 24-29)
and the closed forms called directly. Per paper group (Table 2 presets group1..group6) and draw:

- **campaign**: the six boundary positions with the paper's noise (scale eq. 34, servo eq. 35): the
  distances |O1 O2| at the held angles from the closed forms, from the fast path and from the twin;
- **identification** of the paper's four unknowns (dtheta1, dtheta2, drMx, drMy) from those readings, the
  same estimator on both paths: the paper's eq. 29 (one linearisation at the nominal machine, truncated SVD at
  full rank), unweighted (the CLI default ``--method tsvd``) and generalised least squares (``--method gls``;
  the generic core with :func:`~pmcal.calib.closed_chain.reading_covariance`); and the generic core's own
  estimator, the exact nonlinear least squares (LM, IFT Jacobian, GLS), on the fast path and on the twin.
  Accuracy: RMS over the draws of the zero-offset error (deg);
- **compensation** of 200 target positions with the true errors (closed-form IK vs ``compensate_targets``);
- **evaluation** of a parameter set on a 48-position campaign; **study batch**: 500 chains of 6 positions.

Why the exact estimator's RMS error is *not* the target's measure: with six positions and four unknowns
(condition ~475) the noise (0.5 deg RMS) dominates. The paper's linearisation at the nominal machine is a
linear estimator, biased (noise-free it returns (1.905, -1.172) deg for the true (2, -1) of group 1; the
exact fit returns (1.999, -1.000)) and shrunk along the badly seen direction, so its RMS error can fall
below the Cramér-Rao bound of the true machine, which the unbiased exact fit reaches. The exact fit is
printed beside it with its noise-free bias; the target compares the same estimator on both paths.

Targets (issue 22): generic accuracy <= 1.1x the dedicated, generic time <= 3x, per stage.

Run: python benchmarks/chain_planar_bench.py [--draws 20] [--json PATH]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table, write_json  # noqa: E402
from pmcal.calib.chain_model import NamedModel  # noqa: E402
from pmcal.calib.closed_chain import compensate_targets, identify_chain, reading_covariance  # noqa: E402
from pmcal.calib.planar.design import boundary_positions  # noqa: E402
from pmcal.calib.planar.identification import identify  # noqa: E402
from pmcal.mechanism.machine_spec import MachineSpec  # noqa: E402
from pmcal.mechanism.planar.chain import PlanarChainModel  # noqa: E402
from pmcal.mechanism.planar.kinematics import actual_position, inverse, mm_vector  # noqa: E402
from pmcal.mjcf import machine_dir  # noqa: E402
from pmcal.threads import apply_blas_policy  # noqa: E402
from pmcal.twin.closed_chain import ClosedChainTwin  # noqa: E402
from pmcal.twin.planar.config import default_machine  # noqa: E402

ACCURACY_MAX, TIME_MAX = 1.1, 3.0
GROUPS = tuple(f"group{i}" for i in range(1, 7))
KEYS = ["dtheta1", "dtheta2", "drMx", "drMy"]
#: the paper's eq. 29 on the generic core: one linearisation at the nominal machine, TSVD at full rank
PAPER_ESTIMATOR = dict(method="tsvd", rank=len(KEYS), max_iter=1)
#: identification variants: label -> (path, dedicated method or generic options, weighted)
IDENTIFY = {"paper eq. 29 (TSVD)": ("tsvd", PAPER_ESTIMATOR, False),
            "paper eq. 29 (GLS)": ("gls", PAPER_ESTIMATOR, True)}


def closed_lengths(geom, errors, motor: np.ndarray) -> np.ndarray:
    """|O1 O2| (mm) of the machine with ``errors`` at held motor angles (rad): the paper's eq. 4-8."""
    return np.linalg.norm(mm_vector(geom.perturbed(errors), actual_position(geom, errors, motor)), axis=-1)


#: repetitions of each timed identification on the closed forms and the fast path; the fastest counts
#: (timeit's rule: the slower ones measure the machine's other load, not the code). Single calls elsewhere:
#: a repeated evaluation at the same errors would find the fast path's kept state.
REPEAT = 5


def timed(fn, *args, repeat: int = 1, **kw):
    """``fn(*args, **kw)`` and its wall time in s, the fastest of ``repeat`` runs."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn(*args, **kw)
        best = min(best, time.perf_counter() - t0)
    return out, best


def rms(a) -> float:
    return float(np.sqrt(np.mean(np.square(a))))


def run(draws: int) -> dict:
    machine = default_machine()
    geom, noise = machine.geometry, machine.noise
    spec = MachineSpec.load(machine_dir("planar_2dof") / "chain")
    fast = PlanarChainModel(spec, geom)
    twin = NamedModel(ClosedChainTwin(spec), spec.names)
    r = boundary_positions(machine.workspace, 3)
    cmd = inverse(geom, r)
    cmd_deg = np.rad2deg(cmd)
    motor_sigma = [m.sigma for m in spec.motors]
    cov = reading_covariance(fast, cmd_deg, motor_sigma, noise.scale)
    paths = ("dedicated", "fast", "twin")
    stage = {k: dict.fromkeys(paths, 0.0) for k in ("campaign", *IDENTIFY, "exact LM (GLS)", "compensate",
                                                    "evaluate", "study_batch")}
    err = {k: [] for k in ("ded tsvd", "gen tsvd", "ded gls", "gen gls", "fast lm", "twin lm")}
    rows, max_reading_diff = [], 0.0
    for grp in GROUPS:
        errors = machine.preset(grp)
        truth = errors.as_interface()
        zero = np.array([truth["dtheta1"], truth["dtheta2"]])
        per = {k: [] for k in err}
        for d in range(draws):
            rng = np.random.default_rng(100 * d + GROUPS.index(grp))
            held = cmd + rng.normal(0.0, noise.servo, cmd.shape)
            length, t = timed(closed_lengths, geom, errors, held)
            stage["campaign"]["dedicated"] += t
            readings = np.diff(length) + rng.normal(0.0, noise.scale, len(r) - 1)
            for path, model in (("fast", fast), ("twin", twin)):
                dist, t = timed(model.observe, np.rad2deg(held), truth)
                stage["campaign"][path] += t
                max_reading_diff = max(max_reading_diff, float(np.max(np.abs(dist[:, 0] - length))))
            for label, (method, options, weighted) in IDENTIFY.items():
                ded, t = timed(identify, geom, r, readings, model="simplified", method=method, noise=noise,
                               repeat=REPEAT)
                stage[label]["dedicated"] += t
                gen, t = timed(lambda: identify_chain(      # GLS: the reading covariance made per call, as
                    fast, cmd_deg, readings, keys=KEYS, prior=False,   # the dedicated code does
                    covariance=reading_covariance(fast, cmd_deg, motor_sigma, noise.scale) if weighted else None,
                    **options), repeat=REPEAT)
                stage[label]["fast"] += t
                per[f"ded {method}"].append(np.rad2deg(ded.x[:2]) - zero)
                per[f"gen {method}"].append(np.array([gen.params["dtheta1"], gen.params["dtheta2"]]) - zero)
            stage["exact LM (GLS)"]["dedicated"] = np.nan
            for path, model in (("fast", fast), ("twin", twin)):
                gen, t = timed(identify_chain, model, cmd_deg, readings, keys=KEYS, prior=False, covariance=cov,
                               repeat=REPEAT if path == "fast" else 1)
                stage["exact LM (GLS)"][path] += t
                per[f"{path} lm"].append(np.array([gen.params["dtheta1"], gen.params["dtheta2"]]) - zero)
        for k, v in per.items():
            err[k].append(np.array(v))
        rows.append([grp, *(f"{rms(per[k]):.4f}" for k in err),
                     f"{rms(per['gen tsvd']) / rms(per['ded tsvd']):.4f}",
                     f"{rms(per['gen gls']) / rms(per['ded gls']):.4f}"])
    allerr = {k: np.concatenate(v) for k, v in err.items()}
    acc = {f"{k}_rms_deg": rms(v) for k, v in allerr.items()}
    acc["ratio_tsvd"] = acc["gen tsvd_rms_deg"] / acc["ded tsvd_rms_deg"]
    acc["ratio_gls"] = acc["gen gls_rms_deg"] / acc["ded gls_rms_deg"]
    acc["ratio_exact_lm_to_tsvd"] = acc["fast lm_rms_deg"] / acc["ded tsvd_rms_deg"]
    acc["max_difference_gen_vs_ded_tsvd_deg"] = float(np.max(np.abs(allerr["gen tsvd"] - allerr["ded tsvd"])))
    acc["max_difference_gen_vs_ded_gls_deg"] = float(np.max(np.abs(allerr["gen gls"] - allerr["ded gls"])))
    acc["max_difference_fast_vs_twin_lm_deg"] = float(np.max(np.abs(allerr["fast lm"] - allerr["twin lm"])))

    # noise-free bias of the paper's linearisation and of the exact fit (group 1: offsets 2 and -1 deg)
    errors = machine.preset("group1")
    exact = np.diff(closed_lengths(geom, errors, cmd))
    lin = np.rad2deg(identify(geom, r, exact, model="simplified", method="tsvd").x[:2])
    lm_fit = identify_chain(fast, cmd_deg, exact, keys=KEYS, prior=False)
    acc["noise_free_group1"] = {"truth_deg": [2.0, -1.0], "paper_linearisation_deg": lin.tolist(),
                                "exact_lm_deg": [lm_fit.params["dtheta1"], lm_fit.params["dtheta2"]]}

    # compensation of 200 targets over W with the group-1 errors
    truth = errors.as_interface()
    rng = np.random.default_rng(7)
    task = np.stack([rng.uniform(-240, 240, 200), rng.uniform(-782, -632, 200)], axis=1)
    twin.inverse(task[:5], truth)                             # warm the twin (first solves from home)
    c_ded, stage["compensate"]["dedicated"] = timed(
        lambda: np.rad2deg(inverse(geom.perturbed(errors), task) - errors.dtheta))
    diffs = {}
    for path, model in (("fast", fast), ("twin", twin)):
        c, stage["compensate"][path] = timed(compensate_targets, model, truth, task)
        diffs[path] = float(np.nanmax(np.abs(c - c_ded)))
    stage["compensate"]["max_difference_deg"] = diffs

    # evaluation: the readings a parameter set predicts on a 48-position campaign
    th48 = inverse(geom, boundary_positions(machine.workspace, 24))
    v_ded, stage["evaluate"]["dedicated"] = timed(lambda: np.diff(closed_lengths(geom, errors, th48)))
    diffs = {}
    for path, model in (("fast", fast), ("twin", twin)):
        v, stage["evaluate"][path] = timed(lambda: np.diff(model.observe(np.rad2deg(th48), truth)[:, 0]))
        diffs[path] = float(np.max(np.abs(v - v_ded)))
    stage["evaluate"]["max_difference_mm"] = diffs

    # the study's batch: 500 chains of the six positions at once
    held = (cmd[None] + np.random.default_rng(3).normal(0, noise.servo, (500, 6, 2))).reshape(-1, 2)
    length, stage["study_batch"]["dedicated"] = timed(closed_lengths, geom, errors, held)
    diffs = {}
    for path, model in (("fast", fast), ("twin", twin)):
        dist, stage["study_batch"][path] = timed(model.observe, np.rad2deg(held), truth)
        diffs[path] = float(np.max(np.abs(dist[:, 0] - length)))
    stage["study_batch"]["max_difference_mm"] = diffs
    for label in IDENTIFY:                                    # the paper's estimator: not run on the twin
        stage[label]["twin"] = np.nan
    for v in stage.values():
        v["ratio_fast"] = v["fast"] / v["dedicated"]
        v["ratio_twin"] = v["twin"] / v["dedicated"]
    return {"draws_per_group": draws, "groups": list(GROUPS), "accuracy": acc, "per_group": rows,
            "stages": stage, "campaign_max_reading_difference_mm": max_reading_diff,
            "targets": {"accuracy_max": ACCURACY_MAX, "time_max": TIME_MAX}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--draws", type=int, default=20, help="campaigns per paper group (default 20)")
    ap.add_argument("--json", default=None, help="JSON path (default benchmarks/results/chain_planar_bench.json)")
    a = ap.parse_args(argv)
    apply_blas_policy()
    res = run(a.draws)
    print_table(f"zero-offset error after identification, RMS over {a.draws} draws (deg), same readings",
                ["group", "dedicated TSVD", "generic TSVD", "dedicated GLS", "generic GLS", "exact LM (fast)",
                 "exact LM (twin)", "ratio TSVD", "ratio GLS"], res["per_group"])
    acc = res["accuracy"]
    nf = acc["noise_free_group1"]
    print(f"all groups, the paper's estimator on both paths: TSVD ratio {acc['ratio_tsvd']:.4f}, GLS ratio "
          f"{acc['ratio_gls']:.4f} (target <= {ACCURACY_MAX}); largest difference of the estimates "
          f"{acc['max_difference_gen_vs_ded_tsvd_deg']:.1e} / {acc['max_difference_gen_vs_ded_gls_deg']:.1e} deg")
    print(f"exact LM: {acc['fast lm_rms_deg']:.4f} deg RMS ({acc['ratio_exact_lm_to_tsvd']:.3f}x the paper's "
          f"TSVD; fast path and twin agree to {acc['max_difference_fast_vs_twin_lm_deg']:.1e} deg); noise-free "
          f"group 1 (truth 2, -1 deg): paper {nf['paper_linearisation_deg'][0]:.3f}, "
          f"{nf['paper_linearisation_deg'][1]:.3f}; exact {nf['exact_lm_deg'][0]:.3f}, {nf['exact_lm_deg'][1]:.3f}")
    print(f"campaign readings: closed forms, fast path and twin agree to "
          f"{res['campaign_max_reading_difference_mm']:.1e} mm")
    def cell(x: float, fmt: str) -> str:
        return format(x, fmt) if np.isfinite(x) and x > 0 else "-"

    table = []
    for k, v in res["stages"].items():
        ok = "-" if not np.isfinite(v["ratio_fast"]) else ("yes" if v["ratio_fast"] <= TIME_MAX else "no")
        table.append([k, cell(v["dedicated"] * 1e3, ".1f"), cell(v["fast"] * 1e3, ".1f"),
                      cell(v["twin"] * 1e3, ".1f"), cell(v["ratio_fast"], ".2f"), cell(v["ratio_twin"], ".1f"), ok])
    print_table("time, same work (ms; campaign and identification summed over all draws)",
                ["stage", "dedicated", "generic, fast path", "generic, MuJoCo twin", "ratio fast",
                 "ratio twin", f"fast <= {TIME_MAX}x"], table)
    write_json("chain_planar_bench", res, a.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
