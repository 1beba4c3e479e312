"""Shared output of the benchmark scripts: a printed table and a JSON file in benchmarks/results/."""

from __future__ import annotations

import platform
import time
from pathlib import Path

from pmcal.fileio import write_json as write_json_file

RESULTS = Path(__file__).resolve().parent / "results"


def print_table(title: str, header: list[str], rows: list[list]) -> None:
    cells = [[f"{v:.4g}" if isinstance(v, float) else str(v) for v in row] for row in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) for i, h in enumerate(header)]
    print(f"\n{title}")
    print("  ".join(h.ljust(w) for h, w in zip(header, widths)))
    print("  ".join("-" * w for w in widths))
    for r in cells:
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)))


def write_json(name: str, data: dict, path: str | Path | None = None) -> Path:
    out = Path(path) if path else RESULTS / f"{name}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    data = {"benchmark": name, "machine": platform.machine(), "python": platform.python_version(),
            "when": time.strftime("%Y-%m-%d %H:%M:%S"), **data}
    write_json_file(out, data)
    print(f"\nwrote {out}")
    return out
