"""Bad-input matrix: every command, every machine kind, fed bad input as a new user would; each case
classified.

The cases are data, ``tests/bad_inputs/cases.toml`` (each group expands over its ``machines`` and
``values``). A fixture is built once (campaigns, parameters, targets and tables of every machine kind:
the built-in ``ocpm_2dof``, ``planar_2dof``, ``delta_3dof``, ``hexapod_6dof``, and a copy of the Delta
made as docs/ADDING_A_MACHINE.md says, ``../machines/my_delta``); each case runs ``pmcal`` as a
subprocess in a fresh copy of it (``CASE/work`` is the working folder, ``CASE/keep.txt`` a file of the
user's beside it), under a memory limit and a timeout. Classes, the first that applies:

- ``hang``: not finished within the timeout; ``memory``: killed, or "out of memory";
- ``traceback``: a Python traceback or pmcal's "a bug: please report it";
- ``data lost``: a file of the fixture changed or gone that the case does not name as its output;
- ``staging leftover``: a new hidden file or folder (``.NAME.*``) left behind;
- ``silent wrong success``: exit 0 where the case expects a refusal (2) or a failure (1);
- ``unclear``: the refusal is not one line, or does not say what the case expects (``says``);
- ``wrong refusal``: a good command (``expect = "ok"``) that did not succeed;
- ``ok``.

Run: python benchmarks/bad_input_matrix.py [--only SUBSTRING] [--fast] [--timeout 120] [--memory-gb 4]
     [--jobs 1] [--json PATH]
"""

from __future__ import annotations

import argparse
import hashlib
import os
import re
import resource
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
import tomllib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from benchmarks.common import print_table, write_json  # noqa: E402

CASES = ROOT / "tests" / "bad_inputs" / "cases.toml"
CLASSES = ("ok", "data lost", "silent wrong success", "traceback", "hang", "memory", "staging leftover",
           "unclear", "wrong refusal", "set-up failed")

#: machine kind -> (--machine arguments, file stem of its fixture files)
MACHINES = {
    "ocpm": ([], "o"), "planar": (["--machine", "planar_2dof"], "pl"), "delta": (["--machine", "delta_3dof"], "d"),
    "copy": (["--machine", "../machines/my_delta"], "c"), "hexapod": (["--machine", "hexapod_6dof"], "h"),
}

#: the fixture's command lines per machine kind ({s}: its stem); tables only where a machine has one
FIXTURE = {
    "ocpm": [["targets", "-o", "{s}tg.csv"],
             ["twin", "measure", "--preset", "paper-table2", "--poses", "24", "--seed", "1", "-o", "{s}m.csv"],
             ["identify", "{s}m.csv", "-o", "{s}p.json"],
             ["compensate", "{s}p.json", "--table", "{s}table.json", "--table-version", "7"]],
    "planar": [["targets", "-o", "{s}tg.csv"], ["twin", "measure", "--seed", "1", "-o", "{s}m.csv"],
               ["identify", "{s}m.csv", "-o", "{s}p.json"]],
    "delta": [["targets", "-o", "{s}tg.csv"], ["twin", "measure", "--seed", "3", "-o", "{s}m.csv"],
              ["identify", "{s}m.csv", "-o", "{s}p.json"],
              ["compensate", "{s}p.json", "--table", "{s}table.json", "--grid", "5,5,4", "--table-version", "7"]],
    "hexapod": [["targets", "-o", "{s}tg.csv"], ["twin", "measure", "--seed", "1", "-o", "{s}m.csv"],
                ["identify", "{s}m.csv", "-o", "{s}p.json"]],
}
FIXTURE["copy"] = FIXTURE["delta"]


@dataclass
class Case:
    """One command line and what it must give."""
    id: str
    machine: str
    argv: list[str]
    expect: str                      # ok | refused | failed
    says: list[str] = field(default_factory=list)
    writes: list[str] = field(default_factory=list)     # fixture files (relative to work) it may change
    setup: str = ""                  # shell line run in CASE/work before the command
    fast: bool = False


@dataclass
class Result:
    id: str
    machine: str
    command: str
    klass: str
    status: int | None
    stderr: str
    seconds: float


def load_cases(path: Path = CASES) -> list[Case]:
    """The cases of ``path``: every ``[[group]]`` expanded over its ``machines`` and ``values`` ({v} in
    ``command``, ``setup``, ``says``; {m} the machine's --machine arguments; {meas}, {params}, {targets},
    {table} its fixture files; {data} the repository's tests/data)."""
    doc = tomllib.loads(path.read_text(encoding="utf-8"))
    out: list[Case] = []
    for g in doc["group"]:
        values = g.get("values", [""])
        for machine in g.get("machines", ["ocpm"]):
            margs, stem = MACHINES[machine]
            for k, v in enumerate(values):
                if g.get("other_machines") and _same_machine(str(v), stem):
                    continue                                      # the machine's own file: not a bad input
                subst = {"m": " ".join(margs), "meas": f"{stem}m.csv", "params": f"{stem}p.json",
                         "targets": f"{stem}tg.csv", "table": f"{stem}table.json", "s": stem,
                         "data": str(ROOT / "tests" / "data")}
                subst["v"] = _fill(str(v), subst)
                fill = lambda text: _fill(text, subst)            # noqa: E731
                cid = f"{g['id']}/{machine}" + (f"/{k}" if len(values) > 1 else "")
                out.append(Case(id=cid, machine=machine, argv=shlex.split(fill(g["command"])), expect=g["expect"],
                                says=[fill(s) for s in g.get("says", [])], writes=[fill(w) for w in g.get("writes", [])],
                                setup=fill(g.get("setup", "")), fast=bool(g.get("fast", False)) and k == 0
                                and machine in (g.get("machines", ["ocpm"])[0], "copy")))
    ids = [c.id for c in out]
    dup = {i for i in ids if ids.count(i) > 1}
    if dup:
        raise ValueError(f"{path}: case ids given twice: {sorted(dup)}")
    return out


def _same_machine(value: str, stem: str) -> bool:
    """Whether a file named in ``value`` is of the machine whose fixture files start with ``stem`` (the
    Delta's copy and the Delta share their geometry)."""
    owner = re.match(r"[a-z]+?(?=(m\.csv|p\.json|tg\.csv|table\.json))", value)
    same = {"d": {"d", "c"}, "c": {"d", "c"}}.get(stem, {stem})
    return bool(owner) and owner.group(0) in same


def _fill(text: str, subst: dict[str, str]) -> str:
    """``text`` with each ``{name}`` of ``subst`` replaced (other braces, awk's, left alone)."""
    return re.sub(r"\{(\w+)\}", lambda m: subst.get(m.group(1), m.group(0)), text)


def pmcal_command() -> list[str]:
    return [sys.executable, "-c", "from pmcal.cli import run; run()"]


def fixture_kinds(cases: list[Case]) -> tuple[str, ...]:
    """The machine kinds whose fixture files ``cases`` use (all when one names another machine's file)."""
    if any(c.id.startswith("another-machines") for c in cases):
        return tuple(MACHINES)
    return tuple(k for k in MACHINES if any(c.machine == k for c in cases))


def build_fixture(root: Path, kinds=tuple(MACHINES)) -> Path:
    """The fixture under ``root``: ``machines/my_delta`` (the recipe's copy), ``work`` (every kind's files, a
    sub-folder ``sub`` holding a copy of the ocpm campaign, a notes file), ``keep.txt``."""
    import pmcal.mjcf
    copy = root / "machines" / "my_delta"
    shutil.copytree(pmcal.mjcf.machine_dir("delta_3dof"), copy)
    (copy / "delta_3dof.xml").rename(copy / "my_delta.xml")
    toml = (copy / "machine.toml").read_text(encoding="utf-8")
    toml = toml.replace('name = "delta_3dof"', 'name = "my_delta"').replace('model = "delta_3dof.xml"',
                                                                            'model = "my_delta.xml"')
    (copy / "machine.toml").write_text(toml, encoding="utf-8")
    scene = (copy / "scene.xml").read_text(encoding="utf-8")
    (copy / "scene.xml").write_text(scene.replace('file="delta_3dof.xml"', 'file="my_delta.xml"'), encoding="utf-8")
    work = root / "work"
    (work / "sub").mkdir(parents=True)
    (root / "keep.txt").write_text("the user's file beside the working folder\n")
    (work / "notes.txt").write_text("the user's notes\n")
    for kind in kinds:
        margs, stem = MACHINES[kind]
        for argv in FIXTURE[kind]:
            argv = margs + [a.format(s=stem) for a in argv] + ["--quiet"]
            done = subprocess.run(pmcal_command() + argv, cwd=work, capture_output=True, text=True)
            if done.returncode != 0:
                raise RuntimeError(f"fixture: pmcal {' '.join(argv)}: {done.stderr.strip()}")
    if (work / "om.csv").exists():
        shutil.copy(work / "om.csv", work / "sub" / "om.csv")
    return root


def digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and not p.is_symlink()}


def hidden(root: Path) -> set[str]:
    """Hidden files and folders under ``root`` (staging, temporary files), pmcal's output markers aside."""
    from pmcal.fileio import MARKER
    return {str(p.relative_to(root)) for p in root.rglob(".*") if p.name != MARKER}


def _limit(memory_bytes: int):
    def apply():
        resource.setrlimit(resource.RLIMIT_AS, (memory_bytes, memory_bytes))
        os.setsid()
    return apply


def classify(case: Case, status: int | None, stderr: str, before: dict, after: dict,
             hidden_before: set, hidden_after: set) -> str:
    """The class of one run (module docstring)."""
    if status is None:
        return "hang"
    if status < 0 or "out of memory" in stderr:
        return "memory"
    if "Traceback" in stderr or "a bug: please report" in stderr:
        return "traceback"
    allowed = {f"work/{w}" for w in case.writes}
    if any(k not in after or after[k] != v for k, v in before.items() if k not in allowed):
        return "data lost"
    if hidden_after - hidden_before:
        return "staging leftover"
    lines = [line for line in stderr.splitlines() if line.strip() and not line.startswith("pmcal: warning")]
    if case.expect == "ok":
        return "ok" if status == 0 else "wrong refusal"
    if status == 0:
        return "silent wrong success"
    want = 2 if case.expect == "refused" else 1
    if status != want or len(lines) != 1 or any(s.lower() not in lines[0].lower() for s in case.says):
        return "unclear"
    return "ok"


def run_case(case: Case, fixture: Path, timeout: float, memory_gb: float) -> Result:
    """Run one case in a fresh copy of ``fixture``."""
    with tempfile.TemporaryDirectory(prefix="pmcal-bad-") as tmp:
        root = Path(tmp) / "case"
        shutil.copytree(fixture, root, symlinks=True)
        work = root / "work"
        if case.setup:                               # 'pmcal' on its PATH is this interpreter's
            path = f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"
            done = subprocess.run(["bash", "-c", "set -e; " + case.setup], cwd=work, capture_output=True, text=True,
                                  env=dict(os.environ, PATH=path, MUJOCO_GL="egl"))
            if done.returncode != 0:
                return Result(case.id, case.machine, case.setup, "set-up failed", done.returncode,
                              done.stderr.strip(), 0.0)
        before, hidden_before = digest(root), hidden(root)
        env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"), PMCAL_BLAS_THREADS="1",
                   COLUMNS="200")
        argv = MACHINES[case.machine][0] + case.argv if "--machine" not in case.argv else case.argv
        t0 = time.perf_counter()
        proc = subprocess.Popen(pmcal_command() + argv, cwd=work, env=env, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, preexec_fn=_limit(int(memory_gb * 2**30)))
        try:
            _, stderr = proc.communicate(timeout=timeout)
            status = proc.returncode
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, 9)
            _, stderr = proc.communicate()
            status = None
        seconds = time.perf_counter() - t0
        for p in root.rglob("*"):                    # read-only set-ups: let the copy be removed
            if p.is_dir() and not p.is_symlink():
                p.chmod(0o755)
        klass = classify(case, status, stderr, before, digest(root), hidden_before, hidden(root))
        return Result(case.id, case.machine, "pmcal " + shlex.join(argv), klass, status, stderr.strip(), seconds)


def run(cases: list[Case], fixture: Path, timeout: float = 120.0, memory_gb: float = 4.0,
        jobs: int = 1) -> list[Result]:
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        return list(pool.map(lambda c: run_case(c, fixture, timeout, memory_gb), cases))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", default=None, help="run the cases whose id holds this text")
    ap.add_argument("--fast", action="store_true", help="only the cases marked fast (the default suite's)")
    ap.add_argument("--timeout", type=float, default=120.0, help="seconds per case before it counts as a hang")
    ap.add_argument("--memory-gb", type=float, default=4.0, help="address-space limit per case, GiB")
    ap.add_argument("--jobs", type=int, default=1, help="cases run at once")
    ap.add_argument("--json", default=None, help="JSON to write (default benchmarks/results/bad_input_matrix.json)")
    args = ap.parse_args()
    cases = [c for c in load_cases() if (not args.only or args.only in c.id) and (not args.fast or c.fast)]
    with tempfile.TemporaryDirectory(prefix="pmcal-bad-fixture-") as tmp:
        fixture = build_fixture(Path(tmp), fixture_kinds(cases))
        results = run(cases, fixture, args.timeout, args.memory_gb, args.jobs)
    counts = {k: sum(r.klass == k for r in results) for k in CLASSES}
    bad = [r for r in results if r.klass != "ok"]
    if bad:
        print_table("cases not ok", ["case", "class", "exit", "stderr (first line)"],
                    [[r.id, r.klass, r.status, (r.stderr.splitlines() or [""])[-1][:110]] for r in bad])
    by_machine = sorted({r.machine for r in results})
    print_table(f"bad-input matrix: {len(results)} cases", ["class"] + by_machine + ["all"],
                [[k] + [sum(r.klass == k and r.machine == m for r in results) for m in by_machine] + [counts[k]]
                 for k in CLASSES])
    write_json("bad_input_matrix", {"cases": len(results), "counts": counts, "memory_gb": args.memory_gb,
                                    "timeout_s": args.timeout, "results": [asdict(r) for r in results]}, args.json)
    return 0 if not bad else 1


if __name__ == "__main__":
    sys.exit(main())
