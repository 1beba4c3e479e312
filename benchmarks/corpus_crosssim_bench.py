"""The corpus judged on data pmcal did not generate: each model's campaigns simulated by tests/crosssim_chain (a
second simulator of machine folders written separately from the generic core: its own error parameterisation
written into the MJCF before compiling, its own loop solver on plain MuJoCo), then calibrated as a user does.

Per model and seed: random errors of the toml's sizes in the simulator's own parameters; pmcal's plan of 48
poses (``pmcal.chain.plan``, what a user drives); the simulator's nests plus tracker noise (machine.toml's
``sigma_mm``) written as the measurement CSV; ``pmcal --machine DIR identify`` (exit status, warnings); 24
held-out targets compensated with the identified errors (``pmcal.chain.compensate``) and driven on the
simulator, against the controller's nominal IK driven there too (uncompensated), and the error the
identification predicts. Task errors per family: position (mm) and orientation (deg).

Not computed here: the reference fit in the simulator's own parameters (a finite-difference least-squares fit
costs about 140 parameters x 48 closure solves per Jacobian, hours per seed with this simulator).

Run: python benchmarks/corpus_crosssim_bench.py [--models reachy_mini] [--seeds 5] [--json PATH]
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
from benchmarks.corpus_bench import CORPUS, corpus_arguments, corpus_cases  # noqa: E402
from pmcal.chain import compensate, identify, plan, sample_targets  # noqa: E402
from pmcal.cli import main as pmcal_main  # noqa: E402
from pmcal.errors import InputError  # noqa: E402
from pmcal.io_chain import ChainMeasurements, read_measurements, write_measurements  # noqa: E402
from pmcal.machines import Machine  # noqa: E402
from pmcal.mechanism.task_space import error_families, rms, task_difference  # noqa: E402
from tests.crosssim_chain.machine import SimMachine  # noqa: E402

POSES, HELD_OUT = 48, 24


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
    nests = sim.nests(design.commands)
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
    identified = {k: float(v) for k, v in doc["params"].items()}
    coords = machine.spec.task.coordinates
    task = sample_targets(machine, HELD_OUT, seed=seed + 1000)
    nominal = machine.twin.inverse(task, None)
    try:
        commands = compensate(machine, identified, task)
    except InputError as exc:
        return {**row, "stage": "compensate", "failure": str(exc)}
    before = task_difference(sim.task(nominal), task, coords)
    after = task_difference(sim.task(commands), task, coords)
    # the prediction as the demo makes it (ChainIdentResult.predicted_task_std: the posterior over every error,
    # propagated to the task), from the same identification through the API (the command line's, deterministic)
    res = identify(machine, read_measurements(str(csv), machine.spec))
    predicted = res.predicted_task_std(machine.twin.task_jacobian(commands, res.params, list(res.params)))
    for name, unit, members, size in error_families(coords):
        idx = [i for i, c in enumerate(coords) if c in members]
        row[f"{name}_before_{unit}"] = rms(size(before, coords))
        row[f"{name}_after_{unit}"] = rms(size(after, coords))
        row[f"{name}_predicted_{unit}"] = rms(np.sqrt(np.sum(predicted[:, idx] ** 2, axis=1)))
    row["stage"] = "done"
    row["wall_s"] = time.perf_counter() - t0
    row["simulate_identify_s"] = t_sim
    return row


def main(argv: list[str] | None = None) -> int:
    args, names = corpus_arguments(argv, __doc__, "corpus_crosssim_bench", 5)
    runs, rows = [], []
    for name, seed, tmp in corpus_cases(names, args.seeds):
        r = {"model": name, "seed": seed, **run(CORPUS / name, seed, tmp)}
        runs.append(r)
        fam = "position_%s_mm" if "position_after_mm" in r else "orientation_%s_deg"
        rows.append([name, seed, r["stage"], r.get(fam % "before", ""), r.get(fam % "after", ""),
                     r.get(fam % "predicted", ""), r.get("orientation_after_deg", ""),
                     r.get("orientation_predicted_deg", ""), r.get("chi2_per_dof", ""),
                     len(r.get("warnings", [])), r.get("failure", "")[:90]])
    print_table("corpus on the second simulator (tests/crosssim_chain): task error at held-out targets, "
                "position mm (orientation deg where the task has angles)",
                ["model", "seed", "stage", "before", "after", "predicted", "after deg", "predicted deg",
                 "chi2/dof", "warnings", "failure"], rows)
    write_json("corpus_crosssim_bench", {"poses": POSES, "held_out": HELD_OUT, "runs": runs}, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
