"""Speed where a user waits, before/after in one run (issue 15): compensation, small twin calls,
identification next to a busy pmcal job, the demo.

"before" is the code at ``--before`` (default ad1de20: main before the bordered-Newton compensation;
c5c40e8 is main before the first speed-up), extracted with
``git archive`` into a temporary folder and imported from there; "after" is this working tree. Every
figure is measured in a child process of each version, alternating, so both see the same machine load
(the reference machine has 2 cores shared with other jobs: compare the ratios, not the absolute times).
Children apply pmcal's BLAS thread policy (:mod:`pmcal.threads`) as every entry point does, when their
code has it (a "before" tree older than the policy runs with the libraries' default threads, as it did).

Run: python benchmarks/speed_bench.py [--only compensation,twin,identify,demo] [--demo-repeat 3]
                                      [--repeat 3] [--before REF] [--json PATH]

Each compensation and twin figure is the median over ``--repeat`` alternating child runs; the 200-target
calls with one target out of reach are themselves interleaved with the clean call (median of 9). The
load average (``uptime``) at each figure is printed beside it.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SUBPACKAGES = ("mechanism", "twin", "calib", "bridge", "mjcf", "plc")
#: Interleaved repeats of the 200-target calls (clean / one target out of reach), median reported.
UNREACHABLE_REPEAT = 9


# ------------------------------------------------------------------------------------------ versions
def before_tree(ref: str, dest: Path) -> Path:
    """Importable tree of commit ``ref``: ``dest/pmcal`` with the top-level folders as sub-packages."""
    src = dest / "src"
    src.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", ref], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(src)], input=archive, check=True)
    pkg = dest / "pkg"
    shutil.copytree(src / "pmcal", pkg / "pmcal")
    for sub in SUBPACKAGES:
        (pkg / "pmcal" / sub).symlink_to(src / sub, target_is_directory=True)
    return pkg


def child(version: str, pythonpath: Path | None, *args: str, env: dict | None = None) -> dict:
    """Run ``speed_bench.py --measure ...`` in a fresh interpreter of ``version``; its JSON result."""
    e = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"), **(env or {}))
    e["PYTHONPATH"] = str(pythonpath) if pythonpath else ""
    out = subprocess.run([sys.executable, __file__, "--measure", *args, "--version", version],
                         capture_output=True, text=True, env=e, cwd=ROOT if pythonpath is None else pythonpath)
    if out.returncode:
        raise RuntimeError(f"{version} {args}: {out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


# ------------------------------------------------------------------------------------------ measures
def _policy(version: str) -> None:
    """pmcal's BLAS thread policy, in both versions when the code has it (c5c40e8 has not: its children
    run with the libraries' default threads, as that code did)."""
    try:
        from pmcal.threads import apply_blas_policy
    except ImportError:
        return
    apply_blas_policy()


def _which() -> str:
    import pmcal.twin.ocpm.machine

    return str(Path(pmcal.twin.ocpm.machine.__file__).resolve())


def measure_compensation() -> dict:
    import numpy as np

    try:
        from pmcal.ocpm.compensators import FullCompensation
    except ImportError:                                    # before the split
        from pmcal.apps.ocpm_full import FullCompensation
    from pmcal.mechanism.ocpm.config import default_geometry
    from pmcal.mechanism.ocpm.params import random_errors

    geom = default_geometry()
    params = random_errors(np.random.default_rng(7), 0.5, 0.1)
    comp = FullCompensation(params, None, geom)
    rng = np.random.default_rng(1)
    phi, theta = rng.uniform(0, 360, 1000), rng.uniform(0, 60, 1000)
    comp.commands_deg(phi[:5], theta[:5])                  # warm up (model, batch, tables)
    t = time.perf_counter()
    comp.commands_deg(phi, theta)
    batch = (time.perf_counter() - t) / 1000
    t = time.perf_counter()
    for i in range(30):
        comp.commands_deg(phi[i:i + 1], theta[i:i + 1])
    single = (time.perf_counter() - t) / 30
    pp, tt = np.meshgrid(np.linspace(0, 360, 100), np.linspace(0, 60, 100), indexing="ij")
    t, c = time.perf_counter(), time.process_time()
    comp.commands_deg(pp.ravel(), tt.ravel())
    table, table_cpu = time.perf_counter() - t, time.process_time() - c
    # 200 targets, clean and with one target out of reach, interleaved so that the load hits both alike
    p2, t2 = phi[:200].copy(), theta[:200].copy()
    beyond, band = (p2.copy(), t2.copy()), (p2.copy(), t2.copy())
    beyond[0][100], beyond[1][100] = 200.0, 130.0          # beyond the workspace
    band[0][100], band[1][100] = 40.0, 75.0                # inside it, on a band no solver assembles
    runs = {"clean": [], "beyond": [], "band": []}
    for _ in range(UNREACHABLE_REPEAT):
        for name, (pa, ta) in (("clean", (p2, t2)), ("beyond", beyond), ("band", band)):
            t = time.perf_counter()
            comp.commands_deg(pa, ta)
            runs[name].append(time.perf_counter() - t)
    med = {k: statistics.median(v) for k, v in runs.items()}
    return {"batch_1000_ms_per_target": 1e3 * batch, "single_call_ms_per_target": 1e3 * single,
            "table_100x100_s": table, "table_100x100_cpu_s": table_cpu,
            "200_targets_median_s": med["clean"],
            "200_with_1_beyond_workspace_median_s": med["beyond"],
            "200_with_1_on_singular_band_median_s": med["band"],
            "unreachable_beyond_extra_percent": 100 * (med["beyond"] / med["clean"] - 1),
            "unreachable_band_extra_percent": 100 * (med["band"] / med["clean"] - 1),
            "load_average": os.getloadavg()[0]}


def measure_twin() -> dict:
    import numpy as np

    from pmcal.mechanism.ocpm.params import random_errors
    from pmcal.twin.ocpm.campaign import nominal_commands
    from pmcal.twin.ocpm.machine import Twin

    twin = Twin(random_errors(np.random.default_rng(3), 0.5, 0.1))
    rng = np.random.default_rng(0)
    out = {}
    twin.reach(nominal_commands([10.0], [20.0]))
    for n in (1, 24, 100):
        calls = 40 if n < 100 else 10
        cmds = [nominal_commands(rng.uniform(0, 360, n), rng.uniform(0, 60, n)) for _ in range(calls)]
        t, c0 = time.perf_counter(), time.process_time()
        for c in cmds:
            twin.reach(c)
        dt, cpu = (time.perf_counter() - t) / calls, (time.process_time() - c0) / calls
        out[f"reach_{n}_ms_per_call"] = 1e3 * dt
        out[f"reach_{n}_cpu_ms_per_call"] = 1e3 * cpu
        out[f"reach_{n}_poses_per_s"] = n / dt
    out["load_average"] = os.getloadavg()[0]
    return out


def _identification(n: int = 48, repeat: int = 3) -> float:
    """Median wall time (s) of a whole-chain identification of ``n`` poses."""
    import numpy as np

    from pmcal.calib.ocpm.fullchain import identify_full
    from pmcal.mechanism.ocpm.params import random_errors
    from pmcal.twin.ocpm.campaign import plan_campaign, run_campaign
    from pmcal.twin.ocpm.forward import FullChainModel
    from pmcal.twin.ocpm.machine import Twin
    from pmcal.twin.tracker import LaserTracker

    twin = Twin(random_errors(np.random.default_rng(11), 0.5, 0.1))
    meas = run_campaign(twin, plan_campaign(n, 60, seed=3), LaserTracker(0.01, np.random.default_rng(5)))
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        identify_full(meas, FullChainModel())
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def measure_identify(busy: bool) -> dict:
    return {"identify_48_s": _identification()}


def busy_job(version: str) -> None:
    """A second pmcal job: whole-chain identifications in a loop until killed."""
    _policy(version)
    while True:
        _identification(24, 1)


def measure_demo(version: str) -> dict:
    out = Path(tempfile.mkdtemp(prefix=f"pmcal-demo-{version}-"))
    t = time.perf_counter()
    from pmcal.cli import main

    code = main(["--quiet", "demo", "--out", str(out / "demo")])
    wall = time.perf_counter() - t
    shutil.rmtree(out, ignore_errors=True)
    if code:
        raise RuntimeError(f"demo exited {code}")
    return {"demo_wall_s": wall}


# ------------------------------------------------------------------------------------------ driver
def run_measure(args) -> None:
    if args.measure == "busy":
        busy_job(args.version)
        return
    _policy(args.version)
    fn = {"compensation": measure_compensation, "twin": measure_twin,
          "identify": lambda: measure_identify(False), "demo": lambda: measure_demo(args.version)}[args.measure]
    print(json.dumps({**fn(), "code": _which()}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--only", default="compensation,twin,identify,demo")
    ap.add_argument("--before", default="ad1de20", help="git ref of the 'before' code (default ad1de20)")
    ap.add_argument("--demo-repeat", type=int, default=3)
    ap.add_argument("--repeat", type=int, default=3,
                    help="alternating runs of the compensation and twin measures (median reported)")
    ap.add_argument("--json", default=None)
    ap.add_argument("--measure", help=argparse.SUPPRESS)
    ap.add_argument("--version", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.measure:                   # a child: import pmcal from its PYTHONPATH only, not this tree's root
        sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() not in (ROOT, ROOT / "benchmarks")]
        run_measure(args)
        return
    sys.path.insert(0, str(ROOT))
    from benchmarks.common import print_table, write_json
    only = args.only.split(",")
    tmp = Path(tempfile.mkdtemp(prefix="pmcal-before-"))
    results: dict[str, dict] = {"before_ref": args.before, "command": " ".join(["python"] + sys.argv)}
    rows = []
    try:
        versions = {"before": before_tree(args.before, tmp), "after": None}
        for what in ("compensation", "twin"):
            if what in only:
                runs = {v: [] for v in versions}
                for _ in range(args.repeat):                 # alternating, so both see the same load
                    for v, p in versions.items():
                        runs[v].append(child(v, p, what))
                res = {v: {k: (r[0][k] if k == "code" else statistics.median(x[k] for x in r)) for k in r[0]}
                       for v, r in runs.items()}
                results[what] = {v: {**res[v], "runs": runs[v]} for v in res}
                rows += [[f"{what}: {k}", res["before"].get(k, float("nan")), res["after"][k],
                          f'{res["before"]["load_average"]:.1f} / {res["after"]["load_average"]:.1f}']
                         for k in res["after"] if k not in ("code", "load_average")]
        if "identify" in only:
            res = {}
            for v, p in versions.items():
                idle = child(v, p, "identify")
                print(f"{v}: {idle['code']}")
                idle = idle["identify_48_s"]
                e = dict(os.environ, MUJOCO_GL="egl", PYTHONPATH=str(p) if p else "")
                job = subprocess.Popen([sys.executable, __file__, "--measure", "busy", "--version", v], env=e,
                                       cwd=ROOT if p is None else p, stdout=subprocess.DEVNULL)
                try:
                    time.sleep(3.0)                        # the neighbour is up and computing
                    loaded = child(v, p, "identify")["identify_48_s"]
                finally:
                    job.kill()
                    job.wait()
                res[v] = {"identify_48_idle_s": idle, "identify_48_beside_busy_pmcal_s": loaded,
                          "busy_over_idle": loaded / idle, "load_average": os.getloadavg()[0]}
            results["identify"] = res
            rows += [[f"identification: {k}", res["before"][k], res["after"][k],
                      f'{res["before"]["load_average"]:.1f} / {res["after"]["load_average"]:.1f}']
                     for k in res["after"] if k != "load_average"]
        if "demo" in only:
            walls = {v: [] for v in versions}
            loads = {v: [] for v in versions}
            for _ in range(args.demo_repeat):
                for v, p in versions.items():
                    walls[v].append(child(v, p, "demo")["demo_wall_s"])
                    loads[v].append(os.getloadavg()[0])
            results["demo"] = {v: {"walls_s": w, "median_s": statistics.median(w), "load_averages": loads[v]}
                               for v, w in walls.items()}
            rows.append([f"demo: median wall of {args.demo_repeat}, s", results["demo"]["before"]["median_s"],
                         results["demo"]["after"]["median_s"],
                         f'{statistics.median(loads["before"]):.1f} / {statistics.median(loads["after"]):.1f}'])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    results["load_average"] = os.getloadavg()
    print_table(f"Speed before ({args.before}) / after (this tree); load average {os.getloadavg()[0]:.1f} on "
                f"{os.cpu_count()} cores", ["figure", "before", "after", "load before / after"], rows)
    write_json("speed_bench", results, args.json)


if __name__ == "__main__":
    main()
