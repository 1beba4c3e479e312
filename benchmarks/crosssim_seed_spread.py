"""How much one campaign's compensated error spreads around its estimator's average, on the second simulator's
own linearised machine: whether a per-seed ratio to a reference fit says something about the estimator.

Per model: the second simulator (``tests/crosssim_chain``, nothing of pmcal's model) at its nominal machine;
its nest derivatives by its own errors at a 48-pose plan (``pmcal.chain.plan``, seed 1: the design a user
drives) and its task derivatives at 24 held-out targets, by its implicit-function Jacobian
(``tests.crosssim_chain.reference.jacobian``). Then ``--draws`` campaigns, each: errors drawn from the simulator's
own distribution (normal, the toml's sizes), tracker noise of ``sigma_mm``, and two linear estimates of the
errors from the same nests:

- **bayes**: the posterior mean under that same distribution (what ``identify`` computes in pmcal's own
  parameters; on the corpus bench its compensated error equals the nonlinear Bayes reference to 3 digits);
- **tsvd**: the benchmark's plain least-squares reference (truncated SVD: directions that a prior-sized error
  moves by less than sigma stay at zero).

The compensated task error of each is the task derivative times what it leaves of the errors, RMS over the
held-out targets (in the first task family's units). Printed: the RMS of each over the draws; the share of
single campaigns in which bayes is above 1.5x tsvd; the share of 5-campaign sets in which at least one is; the
share of 5-campaign sets whose RMS ratio is above 1.5x. No timing.

Run: python benchmarks/crosssim_seed_spread.py [--models gepetto_delta,...] [--draws 4000] [--json PATH]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table, write_json  # noqa: E402
from benchmarks.corpus_bench import CORPUS  # noqa: E402
from pmcal.chain import plan, sample_targets  # noqa: E402
from pmcal.machines import Machine  # noqa: E402
from pmcal.mechanism.task_space import error_families  # noqa: E402
from tests.crosssim_chain import reference  # noqa: E402
from tests.crosssim_chain.machine import SimMachine  # noqa: E402

POSES, HELD_OUT, RATIO, SET = 48, 24, 1.5, 5


def linear_machine(folder: Path) -> dict:
    """The simulator's nominal derivatives: nests (N*K*3, P) per prior size in sigma units, task at the
    held-out targets (HELD_OUT, C', P) per prior size in the first task family's coordinates C', that family's
    name and unit, and the number of errors."""
    machine = Machine.from_folder(folder)
    sim = SimMachine(folder)
    design = plan(machine, POSES, seed=1)
    q_plan = sim.solve(design.commands)
    q_task = sim.solve(machine.twin.inverse(sample_targets(machine, HELD_OUT, seed=1001), None))
    s = reference.sizes(sim)
    sigma = machine.spec.sigma_mm
    A = reference.jacobian(sim, q_plan, sim.error_keys, "nests", commands=design.commands) * s / sigma
    T = (reference.jacobian(sim, q_task, sim.error_keys, "task") * s).reshape(HELD_OUT, -1, len(s))
    coords = machine.spec.task.coordinates
    name, unit, members, _ = error_families(coords)[0]
    return {"A": A, "T": T[:, [i for i, c in enumerate(coords) if c in members], :], "family": f"{name} ({unit})",
            "params": len(s)}


def spread(lin: dict, draws: int, seed: int = 0) -> dict:
    """Both estimators' compensated errors over ``draws`` campaigns (see the module's doc)."""
    A, T = lin["A"], lin["T"]
    n = A.shape[1]
    posterior = np.linalg.inv(A.T @ A + np.eye(n))
    U, S, Vt = np.linalg.svd(A, full_matrices=False)
    keep = S >= 1.0
    rng = np.random.default_rng(seed)
    z = rng.normal(size=(draws, n))
    y = z @ A.T + rng.normal(size=(draws, A.shape[0]))
    z_bayes = y @ A @ posterior
    z_tsvd = ((y @ U[:, keep]) / S[keep]) @ Vt[keep]

    def task_rms(z_hat):
        d = np.einsum("tcp,dp->dtc", T, z - z_hat)
        return np.sqrt(np.mean(np.sum(d ** 2, axis=2), axis=1))

    eb, et = task_rms(z_bayes), task_rms(z_tsvd)
    sets = draws // SET
    eb5, et5 = eb[:sets * SET].reshape(sets, SET), et[:sets * SET].reshape(sets, SET)
    return {"family": lin["family"], "params": lin["params"], "tsvd_rank": int(keep.sum()),
            "bayes_rms": float(np.sqrt(np.mean(eb ** 2))), "tsvd_rms": float(np.sqrt(np.mean(et ** 2))),
            "share_above": float(np.mean(eb > RATIO * et)),
            "share_sets_with_one_above": float(np.mean((eb5 > RATIO * et5).any(axis=1))),
            "share_sets_rms_above": float(np.mean(np.sqrt(np.mean(eb5 ** 2, 1) / np.mean(et5 ** 2, 1)) > RATIO))}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="gepetto_delta", help="comma-separated corpus names")
    ap.add_argument("--draws", type=int, default=4000)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    out = {}
    for name in args.models.split(","):
        out[name] = spread(linear_machine(CORPUS / name), args.draws)
        print(f"{name}: done", file=sys.stderr, flush=True)
    print_table(f"one campaign against the average, {args.draws} linearised campaigns per model on the second "
                f"simulator: bayes (the posterior mean, what identify computes) and tsvd (the plain least-squares "
                f"reference)", ["model", "family", "params", "tsvd rank", "RMS bayes", "RMS tsvd",
                                f"bayes > {RATIO}x tsvd", f"sets of {SET} with one", f"sets of {SET}, RMS ratio"],
                [[m, r["family"], r["params"], r["tsvd_rank"], r["bayes_rms"], r["tsvd_rms"], r["share_above"],
                  r["share_sets_with_one_above"], r["share_sets_rms_above"]] for m, r in out.items()])
    write_json("crosssim_seed_spread", {"draws": args.draws, "poses": POSES, "held_out": HELD_OUT, "models": out},
               args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
