"""Count the package's machine-specific Python: lines that serve one seeded machine only (issue 22, item 5).

Usage::

    python tools/machine_code_lines.py [--root DIR] [--json OUT.json] [--files]

Rule, applied to every ``.py`` file of the package (the folders of ``[tool.setuptools.package-dir]``:
``pmcal/``, ``mechanism/``, ``twin/``, ``calib/``, ``bridge/``, ``mjcf/``, ``plc/``; not tests, benchmarks,
tools):

1. **seeds**: a file in a machine's own folder or named after it serves that machine: ``mechanism/<m>/``,
   ``twin/<m>/``, ``calib/<m>/``, ``pmcal/io_<m>.py``, ``pmcal/apps/<m>*.py`` (``<m>`` = ``ocpm`` for
   ``ocpm_2dof``, ``planar`` for ``planar_2dof``).
2. **serving one machine**: any other file that imports (``import`` / ``from ... import`` anywhere in the
   file, functions included) the seed modules of exactly one machine counts for that machine; one that
   imports both machines' seeds counts as ``both`` (the seeded machines' shared layer). One step only: a
   generic module that imports such a file (the chain core importing a shared solver) stays generic.
3. **used by one machine only**: a file every importer of which (at least one, in the package) counts for
   the same machine counts for it too (iterated to a fixed point): a helper only that machine's code uses.

Lines are physical lines (``wc -l``). The table prints, per machine, the lines of each top-level folder
and the total, and the share of the package. Deterministic: the same tree gives the same table.
"""

from __future__ import annotations

import argparse
import ast
import json
import sys
from pathlib import Path

#: import prefix -> repository folder (pyproject.toml [tool.setuptools.package-dir])
PACKAGE_DIRS = {"pmcal.mechanism": "mechanism", "pmcal.twin": "twin", "pmcal.calib": "calib",
                "pmcal.bridge": "bridge", "pmcal.mjcf": "mjcf", "pmcal.plc": "plc", "pmcal": "pmcal"}
#: machine -> the short name of its folders and files
MACHINES = {"ocpm_2dof": "ocpm", "planar_2dof": "planar"}


def package_files(root: Path) -> list[Path]:
    out = []
    for folder in sorted(set(PACKAGE_DIRS.values())):
        out += sorted(p for p in (root / folder).rglob("*.py") if "__pycache__" not in p.parts)
    return out


def module_file(root: Path, module: str) -> Path | None:
    """The repository file of an import name (a module or a package's __init__), or None (outside)."""
    for prefix, folder in sorted(PACKAGE_DIRS.items(), key=lambda kv: -len(kv[0])):
        if module == prefix or module.startswith(prefix + "."):
            rest = module[len(prefix):].lstrip(".").split(".") if module != prefix else []
            base = root / folder / Path(*rest) if rest else root / folder
            for cand in (base.with_suffix(".py"), base / "__init__.py"):
                if cand.is_file():
                    return cand
            return None
    return None


def imports_of(root: Path, path: Path) -> set[Path]:
    """Repository files ``path`` imports (absolute and relative imports, anywhere in the file)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    rel = path.relative_to(root)
    here = None
    for prefix, folder in PACKAGE_DIRS.items():
        if rel.parts[0] == folder:
            here = [prefix] + list(rel.parent.parts[1:])
    out: set[Path] = set()
    for node in ast.walk(tree):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join((here or [])[: len(here or []) - node.level + 1])
                mod = f"{base}.{node.module}" if node.module else base
            else:
                mod = node.module or ""
            names = [mod] + [f"{mod}.{a.name}" for a in node.names]
        for n in names:
            f = module_file(root, n)
            if f is not None and f != path:
                out.add(f)
    return out


def seed_machine(root: Path, path: Path) -> str | None:
    rel = path.relative_to(root).as_posix()
    for machine, short in MACHINES.items():
        if any(rel.startswith(f"{top}/{short}/") for top in ("mechanism", "twin", "calib")):
            return machine
        if rel == f"pmcal/io_{short}.py" or (rel.startswith(f"pmcal/apps/{short}") and rel.endswith(".py")):
            return machine
    return None


def classify(root: Path) -> dict[Path, str]:
    """file -> ``"ocpm_2dof"``, ``"planar_2dof"``, ``"both"`` or ``"generic"`` (module docstring)."""
    files = package_files(root)
    deps = {f: imports_of(root, f) for f in files}
    seed = {f: seed_machine(root, f) for f in files}
    label = {}
    for f in files:
        direct = {seed[d] for d in deps[f]} - {None}
        label[f] = seed[f] or ("both" if len(direct) > 1 else next(iter(direct)) if direct else "generic")
    users = {f: [g for g in files if f in deps[g]] for f in files}
    changed = True
    while changed:
        changed = False
        for f in files:
            if label[f] != "generic" or not users[f]:
                continue
            by = {label[u] for u in users[f]}
            if len(by) == 1 and by <= set(MACHINES):
                label[f], changed = by.pop(), True
    return label


def count(root: Path) -> dict:
    label = classify(root)
    lines = {f: len(f.read_text(encoding="utf-8").splitlines()) for f in label}
    total = sum(lines.values())
    rows = {}
    for group in (*MACHINES, "both", "generic"):
        per_top: dict[str, int] = {}
        for f, g in label.items():
            if g == group:
                top = f.relative_to(root).parts[0]
                per_top[top] = per_top.get(top, 0) + lines[f]
        n = sum(per_top.values())
        rows[group] = {"lines": n, "share": n / total if total else 0.0, "by_folder": dict(sorted(per_top.items())),
                       "files": sorted(f.relative_to(root).as_posix() for f, g in label.items() if g == group)}
    return {"root": str(root), "total_lines": total, "groups": rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default=str(Path(__file__).resolve().parents[1]), help="repository root")
    ap.add_argument("--json", help="write the counts (with the file lists) to this JSON file")
    ap.add_argument("--files", action="store_true", help="also list the files of each machine")
    args = ap.parse_args(argv)
    res = count(Path(args.root).resolve())
    folders = sorted(set(PACKAGE_DIRS.values()))
    print(f"{'group':<12} {'lines':>7} {'share':>6}  " + " ".join(f"{t:>8}" for t in folders))
    for group, row in res["groups"].items():
        print(f"{group:<12} {row['lines']:>7} {row['share']:>6.1%}  "
              + " ".join(f"{row['by_folder'].get(t, 0):>8}" for t in folders))
    print(f"{'package':<12} {res['total_lines']:>7}")
    if args.files:
        for group in MACHINES:
            print(f"\n{group}:")
            for f in res["groups"][group]["files"]:
                print(f"  {f}")
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
