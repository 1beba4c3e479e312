"""The corpus judged on data pmcal did not generate: each model's campaigns simulated by tests/crosssim_chain (a
second simulator of machine folders written separately from the generic core: its own error parameterisation
written into the MJCF before compiling, its own loop solver on plain MuJoCo), then calibrated as a user does.

Per model and seed: random errors of the toml's sizes in the simulator's own parameters; pmcal's plan of 48
poses (``pmcal.chain.plan``, what a user drives); the simulator's nests plus tracker noise (machine.toml's
``sigma_mm``) written as the measurement CSV; ``pmcal --machine DIR identify`` (exit status, warnings); 24
held-out targets compensated with the identified errors (``pmcal.chain.compensate``) and driven on the
simulator, against the controller's nominal IK driven there too (uncompensated), and the error the
identification predicts. Task errors per family: position (mm) and orientation (deg).

The reference (issue 34): a plain least-squares fit of the simulator's own errors (44 to 300 of them) to the same
noisy nests (``tests.crosssim_chain.reference.fit``: scipy ``least_squares`` from zero errors, no prior, scaled by
the prior sizes, in the row space the data determine: singular directions moving the nests by less than the
tracker's sigma per prior size stay at zero), then the held-out targets compensated with it (Gauss-Newton on the
commands of the simulator with the fitted errors, from the nominal IK) and driven on the simulator: ``reference``,
in the families and units of ``after``. Full nonlinear, not linearised: warm-started closures and a Jacobian by
the implicit-function theorem (the closure's partials at fixed joints, no closure solve per parameter) make it
seconds to minutes per seed. ``bayes``: the same with every error and the simulator's own prior (the
distribution its errors are drawn from), the posterior mode: the best a calibration can do on average knowing
that distribution, a yardstick for whether a per-seed ratio is the estimator's or the campaign's. ``ratio`` =
after / reference (the worst family); ``verdict``: ``ok`` (ratio <= 1.5),
``above 1.5x``, ``WORSE`` (identify exited 0 and after > before in a family), or ``refused`` (the model refused at
load, identify exit != 0, quality ``usable`` false, or compensation refused; with its reason).

Run: python benchmarks/corpus_crosssim_bench.py [--corpus DIR] [--models reachy_mini] [--seeds 5] [--json PATH]
"""

from __future__ import annotations

import contextlib
import io
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table, write_json  # noqa: E402
from benchmarks.corpus_bench import corpus_arguments, corpus_cases  # noqa: E402
from pmcal.chain import compensate, identify, plan, sample_targets  # noqa: E402
from pmcal.cli import main as pmcal_main  # noqa: E402
from pmcal.errors import InputError  # noqa: E402
from pmcal.io_chain import ChainMeasurements, read_measurements, write_measurements  # noqa: E402
from pmcal.machines import Machine  # noqa: E402
from pmcal.mechanism.task_space import error_families, rms, task_difference  # noqa: E402
from tests.crosssim_chain import reference  # noqa: E402
from tests.crosssim_chain.machine import SimMachine  # noqa: E402

POSES, HELD_OUT = 48, 24
RATIO = 1.5             # the acceptance line: after within 1.5x the reference


def tasks_at(sim: SimMachine, qs: np.ndarray) -> np.ndarray:
    """The simulator's task coordinates (N, C) at its closed configurations ``qs`` (as ``sim.task``)."""
    return np.array([reference._outputs(sim, q, "task")[1] if np.isfinite(q).all()
                     else np.full(len(sim.coordinates), np.nan) for q in qs])


def reference_fit(folder: Path, sim: SimMachine, design_commands, qs, nests, sigma_mm, task, nominal, q_nominal,
                  coords, prior: bool = False) -> tuple[dict, np.ndarray]:
    """The plain least-squares reference in the simulator's own errors (see the module's doc), or with
    ``prior`` the Bayes reference (the posterior mode under the simulator's own error distribution): ({figures},
    task differences (N, C) at the held-out targets driven with its commands on the simulator ``sim``)."""
    name = "bayes" if prior else "reference"
    t0 = time.perf_counter()
    ref = reference.fit(SimMachine(folder), design_commands, nests, qs, sigma_mm, prior=prior)
    t_fit = time.perf_counter() - t0
    fitted = reference.variant(SimMachine(folder), ref["errors"])
    commands = reference.inverse(fitted, task, nominal, q_nominal)
    reached = task_difference(tasks_at(fitted, reference.close_from(fitted, q_nominal, commands)), task, coords)
    # driven on the simulator: its closure from its own configurations at the nominal commands (the same
    # assembly as sim.task's from home, which costs 20 s per seed on the WL16)
    diff = task_difference(tasks_at(sim, reference.close_from(sim, q_nominal, commands)), task, coords)
    return {f"{name}_rank": ref["rank"], f"{name}_params": ref["n_params"], f"{name}_nfev": ref["nfev"],
            f"{name}_status": ref["status"], f"{name}_rms_residual_mm": ref["rms_residual_mm"],
            f"{name}_polish_cost_change": ref["polish_cost_change"],
            f"{name}_inverse_max_residual": float(np.nanmax(np.abs(reached))),
            f"{name}_fit_s": t_fit, f"{name}_s": time.perf_counter() - t0}, diff


def verdict(row: dict) -> tuple[str, float | None]:
    """(verdict, the worst family's after / reference) of a run (see the module's doc)."""
    if row.get("stage") == "simulate":
        return "not simulated", None
    if row.get("stage") != "done":
        return "refused", None
    if "reference_failure" in row:
        return "no reference", None
    fams = [k.replace("_after_", "_%s_") for k in row if "_after_" in k]
    ratio = max(row[f % "after"] / row[f % "reference"] for f in fams)
    if not row.get("usable", True):
        return "refused", ratio
    if any(row[f % "after"] > row[f % "before"] for f in fams):
        return "WORSE", ratio
    return ("ok" if ratio <= RATIO else f"above {RATIO}x"), ratio


def run(folder: Path, seed: int, tmp: Path) -> dict:
    machine = Machine.from_folder(folder)
    try:
        machine.twin
    except InputError as exc:
        return {"stage": "load", "failure": str(exc)}
    rng = np.random.default_rng(seed)
    sim = SimMachine(folder)
    sim = SimMachine(folder, sim.random_errors(rng))
    t0 = time.perf_counter()
    design = plan(machine, POSES, seed=seed)
    qs = sim.solve(design.commands)
    nests = np.array([sim._sites(q, sim.target_ids) for q in qs])             # sim.nests, its configurations kept
    ok = np.isfinite(nests).all(axis=(1, 2))
    if not ok.all():
        return {"stage": "simulate", "failure": f"{int((~ok).sum())} planned poses do not assemble on the simulator"}
    nests = nests + rng.normal(0.0, machine.spec.sigma_mm, nests.shape)
    meas = ChainMeasurements(pose_id=[f"P{i + 1}" for i in range(len(nests))], commands=design.commands,
                             targets=nests, time_s=np.arange(len(nests)) * 30.0)
    csv, params = tmp / "m.csv", tmp / "p.json"
    write_measurements(csv, machine.spec, meas, [f"crosssim_chain campaign, seed {seed}"])
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = pmcal_main(["--machine", str(folder), "identify", str(csv), "-o", str(params)])
    t_sim = time.perf_counter() - t0
    row = {"identify_exit": status, "identify": out.getvalue().strip().splitlines()[:1],
           "warnings": [x for x in err.getvalue().splitlines() if "warning" in x]}
    if status != 0:
        return {**row, "stage": "identify", "failure": err.getvalue().strip().splitlines()[-1]}
    doc = json.loads(params.read_text())
    row["chi2_per_dof"] = doc["chi2_per_dof"]
    quality = doc.get("quality") if isinstance(doc.get("quality"), dict) else {}
    row["usable"] = quality.get("usable", True) is not False
    if not row["usable"]:
        row["failure"] = f"quality usable false: {quality.get('why', '')}"
    identified = {k: float(v) for k, v in doc["params"].items()}
    coords = machine.spec.task.coordinates
    task = sample_targets(machine, HELD_OUT, seed=seed + 1000)
    nominal = machine.twin.inverse(task, None)
    try:
        commands = compensate(machine, identified, task)
    except InputError as exc:
        return {**row, "stage": "compensate", "failure": str(exc)}
    q_nominal = sim.solve(nominal)
    before = task_difference(tasks_at(sim, q_nominal), task, coords)
    after = task_difference(sim.task(commands), task, coords)
    diffs = {}
    for prior in (False, True):
        name = "bayes" if prior else "reference"
        try:
            figures, diffs[name] = reference_fit(folder, sim, design.commands, qs, nests, machine.spec.sigma_mm,
                                                 task, nominal, q_nominal, coords, prior=prior)
        except Exception as exc:                               # noqa: BLE001 - a benchmark row, not a crash
            figures, diffs[name] = {f"{name}_failure": repr(exc)}, np.full_like(after, np.nan)
        row.update(figures)
    # the prediction as the demo makes it (ChainIdentResult.predicted_task_std: the posterior over every error,
    # propagated to the task), from the same identification through the API (the command line's, deterministic)
    res = identify(machine, read_measurements(str(csv), machine.spec))
    predicted = res.predicted_task_std(machine.twin.task_jacobian(commands, res.params, list(res.params)))
    for name, unit, members, size in error_families(coords):
        idx = [i for i, c in enumerate(coords) if c in members]
        row[f"{name}_before_{unit}"] = rms(size(before, coords))
        row[f"{name}_after_{unit}"] = rms(size(after, coords))
        row[f"{name}_predicted_{unit}"] = rms(np.sqrt(np.sum(predicted[:, idx] ** 2, axis=1)))
        row[f"{name}_reference_{unit}"] = rms(size(diffs["reference"], coords))
        row[f"{name}_bayes_{unit}"] = rms(size(diffs["bayes"], coords))
    row["stage"] = "done"
    row["wall_s"] = time.perf_counter() - t0
    row["simulate_identify_s"] = t_sim
    return row


def summary(runs: list[dict]) -> dict:
    """Per model, over its completed seeds, in the first family's units: the RMS of the compensated error
    (``after``), of the plain least-squares reference's and of the Bayes reference's, and their ratios. Where one
    weakly seen direction dominates the task error (gepetto_delta: one direction carries 98 % of the predicted
    variance, the nests see a prior-sized move of it at 0.4 sigma), one campaign's figure is a draw of about
    one degree of freedom for every estimator: per seed the truncated fit beats the Bayes-optimal one by more
    than 1.5x in about one campaign in six, while its RMS over seeds is larger. The RMS over seeds is what an
    estimator can be held to; the per-seed ratios stay in the rows."""
    out = {}
    for name in dict.fromkeys(r["model"] for r in runs):
        done = [r for r in runs if r["model"] == name and r.get("stage") == "done"]
        fam = next((k.replace("_after_", "_%s_") for r in done for k in r if "_after_" in k), None)
        if fam is None:
            out[name] = {"done": 0}
            continue

        def rms_of(what: str) -> float:
            return float(np.sqrt(np.nanmean([r.get(fam % what, np.nan) ** 2 for r in done])))

        a, ref, bay = rms_of("after"), rms_of("reference"), rms_of("bayes")
        out[name] = {"done": len(done), "family": fam % "rms", "after": a, "reference": ref, "bayes": bay,
                     "after_over_reference": a / ref, "after_over_bayes": a / bay, "bayes_over_reference": bay / ref,
                     "seeds_above_ratio": sum(1 for r in done if (r.get("ratio") or 0) > RATIO)}
    return out


def main(argv: list[str] | None = None) -> int:
    args, names = corpus_arguments(argv, __doc__, "corpus_crosssim_bench", 5)
    runs, rows = [], []
    for name, seed, tmp in corpus_cases(names, args.seeds):
        r = {"model": name, "seed": seed, **run(args.corpus / name, seed, tmp)}
        r["verdict"], r["ratio"] = verdict(r)
        runs.append(r)
        print(f"{name} seed {seed}: {r['verdict']} ({r.get('wall_s', 0):.0f} s)", file=sys.stderr, flush=True)
        with contextlib.redirect_stdout(io.StringIO()):         # the runs so far, should a long run be stopped
            write_json("corpus_crosssim_bench", {"poses": POSES, "held_out": HELD_OUT, "partial": True, "runs": runs},
                       args.json)
        fam = "position_%s_mm" if "position_after_mm" in r else "orientation_%s_deg"
        deg = "orientation_%s_deg" if fam.startswith("position") else "none%s"
        rows.append([name, seed, r["stage"], r.get(fam % "before", ""), r.get(fam % "after", ""),
                     r.get(fam % "reference", ""), r.get(fam % "bayes", ""), r.get(fam % "predicted", ""),
                     r.get(deg % "before", ""), r.get(deg % "after", ""), r.get(deg % "reference", ""),
                     "" if r["ratio"] is None else r["ratio"], r["verdict"], r.get("chi2_per_dof", ""),
                     len(r.get("warnings", [])), r.get("failure", "")[:90]])
    print_table("corpus on the second simulator (tests/crosssim_chain): task error at held-out targets, "
                "position mm (orientation deg where the task has angles; an orientation-only task's in the first "
                "columns), reference = plain least squares in the simulator's own errors",
                ["model", "seed", "stage", "before", "after", "reference", "bayes", "predicted", "before deg",
                 "after deg", "reference deg", "ratio", "verdict", "chi2/dof", "warnings", "failure"], rows)
    per_model = summary(runs)
    print_table(f"per model over its seeds: RMS of the compensated error, of the plain least-squares reference and "
                f"of the Bayes reference (the posterior mode under the simulator's own error distribution); "
                f"seeds above {RATIO}x the reference",
                ["model", "seeds", "after", "reference", "bayes", "after/reference", "after/bayes",
                 "bayes/reference", f"seeds > {RATIO}x"],
                [[m, s["done"], s.get("after", ""), s.get("reference", ""), s.get("bayes", ""),
                  s.get("after_over_reference", ""), s.get("after_over_bayes", ""), s.get("bayes_over_reference", ""),
                  s.get("seeds_above_ratio", "")] for m, s in per_model.items()])
    write_json("corpus_crosssim_bench", {"poses": POSES, "held_out": HELD_OUT, "runs": runs, "per_model": per_model},
               args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
