"""The import contract of pmcal, read from the sources with :mod:`ast` (no import is executed).

Layers, lowest first; a module may import its own layer and the layers below it, never above. Two
further rules: the identification layer reaches the physics only through
:class:`pmcal.calib.ocpm.forward_model.ForwardModel` (``pmcal.calib`` never imports ``pmcal.twin``), and the
bridge depends on no numerics (``pmcal.bridge`` imports neither ``pmcal.calib`` nor ``pmcal.twin``).
Imports inside functions count like any other: a lazy import may not hide a dependency.
docs/DEVELOPING.md shows the same table.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: import name -> folder of the repository (pyproject's package-dir).
FOLDERS = {"pmcal": "pmcal", "pmcal.mechanism": "mechanism", "pmcal.twin": "twin", "pmcal.calib": "calib",
           "pmcal.bridge": "bridge", "pmcal.mjcf": "mjcf", "pmcal.plc": "plc"}
#: (layer name, module prefixes), lowest first. The most specific prefix decides a module's layer.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("foundation", ("pmcal.errors", "pmcal.fileio", "pmcal.progress", "pmcal.csvio", "pmcal.threads",
                    "pmcal.mjcf", "pmcal.plc")),
    ("machine description", ("pmcal.mechanism",)),
    ("twin", ("pmcal.twin",)),
    ("identification and compensation", ("pmcal.calib",)),
    ("bridge", ("pmcal.bridge",)),
    # the application, in its own sub-layers: file formats, the library API, reports, the applications of
    # the machines (their commands' handlers and studies), the command parsers, the entry point
    ("application: file formats", ("pmcal.ocpm.io", "pmcal.io_chain", "pmcal.planar.io", "pmcal.io_tracker")),
    ("application: library", ("pmcal",)),
    ("application: reports", ("pmcal.reports",)),
    ("application: apps", ("pmcal.apps", "pmcal.studies")),
    ("application: commands", ("pmcal.commands",)),
    ("application: cli", ("pmcal.cli", "pmcal.console")),
]
#: (importer prefix, forbidden prefix, why)
FORBIDDEN = [
    ("pmcal.calib", "pmcal.twin", "identification reaches the twin only through calib.forward_model"),
    ("pmcal.bridge", "pmcal.calib", "the bridge is transport: it depends on the table type only"),
    ("pmcal.bridge", "pmcal.twin", "the bridge is transport: it depends on the table type only"),
]


#: The seeded machines' code ("wings"): the modules of each, by prefix. Generic modules import no wing and
#: wings do not import each other; only the library's front door (:data:`FRONT_DOORS`) routes to them.
WINGS: dict[str, tuple[str, ...]] = {
    "ocpm_2dof": ("pmcal.mechanism.ocpm", "pmcal.twin.ocpm", "pmcal.calib.ocpm", "pmcal.ocpm", "pmcal.apps.ocpm",
                  "pmcal.reports.ocpm", "pmcal.studies.ocpm"),
    "planar_2dof": ("pmcal.mechanism.planar", "pmcal.twin.planar", "pmcal.calib.planar", "pmcal.planar",
                    "pmcal.apps.planar"),
}
#: The library API: ``pmcal.read_measurements(path, machine)`` and ``pmcal.identify(campaign)`` route a
#: campaign to its machine's code, so it may import every wing.
FRONT_DOORS = ("pmcal.api",)


def wing_of(module: str) -> str | None:
    """The seeded machine whose code ``module`` is (a module, or a name inside one), None for generic code."""
    for name, prefixes in WINGS.items():
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return name
    return None


def wing_violations(sources: dict[str, str]) -> list[Violation]:
    """Generic modules importing a wing, and wings importing each other (:data:`WINGS`)."""
    bad = []
    for mod, src in sources.items():
        mine = wing_of(mod)
        if mod in FRONT_DOORS:
            continue
        for imp, line in imports_of(mod, src):
            theirs = wing_of(imp)
            if theirs is not None and theirs != mine:
                why = (f"generic code may not import {theirs}'s code" if mine is None
                       else f"{mine}'s code may not import {theirs}'s")
                bad.append(Violation(mod, imp, line, why))
    return bad


def layer_of(module: str) -> int:
    best, rank = -1, -1
    for i, (_, prefixes) in enumerate(LAYERS):
        for p in prefixes:
            if (module == p or module.startswith(p + ".")) and len(p) > best:
                best, rank = len(p), i
    return rank


def modules() -> dict[str, Path]:
    """Every module of pmcal: import name -> source file."""
    out = {}
    for name, folder in FOLDERS.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = list(path.relative_to(ROOT / folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join([name] + parts)] = path
    return out


@dataclass(frozen=True)
class Violation:
    importer: str
    imported: str
    line: int
    why: str

    def __str__(self) -> str:
        return f"{self.importer}:{self.line} imports {self.imported}: {self.why}"


def imports_of(module: str, source: str) -> list[tuple[str, int]]:
    """Absolute pmcal modules ``module`` imports (relative imports resolved), with line numbers."""
    out = []
    is_pkg = False
    pkg = module if is_pkg else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            out += [(f"{base}.{a.name}" if base else a.name, node.lineno) for a in node.names]
    return [(m, ln) for m, ln in out if m == "pmcal" or m.startswith("pmcal.")]


def check(sources: dict[str, str]) -> list[Violation]:
    """Violations of the contract among ``sources`` (import name -> source text)."""
    bad = []
    for mod, src in sources.items():
        mine = layer_of(mod)
        for imp, line in imports_of(mod, src):
            theirs = layer_of(imp)
            if theirs > mine:
                bad.append(Violation(mod, imp, line, f"layer '{LAYERS[mine][0]}' may not import the higher "
                                                     f"layer '{LAYERS[theirs][0]}'"))
            for who, what, why in FORBIDDEN:
                if (mod == who or mod.startswith(who + ".")) and (imp == what or imp.startswith(what + ".")):
                    bad.append(Violation(mod, imp, line, why))
    return bad
