"""The twin's derivative against central differences of its own solve, on every corpus model and built-in machine.

Per machine: random errors of its machine.toml's sizes (seed 3), 12 drawn poses, the nests' Jacobian by the
implicit-function theorem (:meth:`pmcal.twin.closed_chain.ClosedChainTwin.jacobian`) against central
differences of :meth:`targets` at 1e-3 of each error's prior size. Figure: the largest difference, in tracker
sigmas per prior-size error (what a fit would see), and the error key it is on; the Jacobian's time.

Machines whose loops leave a passive direction free (``n_free`` > 0) are listed but not judged: their solves
leave the free direction where the warm start put it, so two solves of nearby errors may differ by that
choice (up to 1e-3 mm on gepetto_wl16, far below the tracker noise but not a derivative): central
differences there measure the solver's history, not the derivative.

Run: python benchmarks/derivative_bench.py [--poses 12] [--json PATH]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import print_table, write_json  # noqa: E402
from tests.chain_references import central_differences  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def folders() -> list[Path]:
    """The corpus models (tests/corpus) and the built-in machine folders (mjcf) with a machine.toml."""
    found = sorted(p.parent for p in (ROOT / "tests" / "corpus").glob("*/machine.toml"))
    found += sorted(p.parent for p in (ROOT / "mjcf").glob("*/machine.toml"))
    found += sorted(p.parent for p in (ROOT / "mjcf").glob("*/chain/machine.toml"))
    return found


def check(folder: Path, poses: int) -> list:
    from pmcal.chain import random_errors
    from pmcal.errors import InputError
    from pmcal.machines import Machine

    name = str(folder.relative_to(ROOT))
    try:
        machine = Machine.from_folder(folder)
        twin = machine.twin
        _ = twin.error_keys
    except (InputError, AttributeError) as exc:
        return [name, "-", "-", "-", "-", f"refused at load ({str(exc)[:60]}...)", "-"]
    rng = np.random.default_rng(3)
    params = random_errors(machine, rng)
    cmd = twin.sample_commands(poses, rng)
    keys = list(twin.error_keys)
    prior = twin.prior_std()
    t0 = time.perf_counter()
    J = twin.jacobian(cmd, params)
    wall = time.perf_counter() - t0
    ref = central_differences(lambda p: twin.targets(cmd, p), params, keys, h=dict(zip(keys, 1e-3 * prior)))
    diff = np.abs(J - ref) * prior / twin.sigma_mm
    per_key = np.nanmax(diff.reshape(-1, len(keys)), axis=0)
    worst = int(np.nanargmax(per_key))
    verdict = "free directions: not judged" if twin.n_free else ("exact" if per_key[worst] < 1e-3 else "OFF")
    return [name, len(keys), twin.n_free, float(per_key[worst]), keys[worst], verdict, wall]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--poses", type=int, default=12)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    rows = []
    for folder in folders():
        rows.append(check(folder, args.poses))
        print(f"\r{len(rows)} machines", end="", flush=True)
    print()
    header = ["machine", "errors", "free directions", "largest |IFT - central| (sigmas)", "on", "verdict",
              "jacobian s"]
    print_table(f"The twin's derivative against central differences of the solve ({args.poses} poses)", header, rows)
    write_json("derivative_bench", {"header": header, "rows": rows}, args.json)
    return 0 if all(r[5] != "OFF" for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
