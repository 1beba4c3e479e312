"""The commissioning docs cannot drift from the PLC sources: every status and state they list has the
value and name of E_CompTableStatus / E_CompTableState (parsed from plc/DUTs), every enum value is
listed, and the interface and format versions they name are GVL_CompTableParam's."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import pmcal.plc
from pmcal.plc import constant as plc_constant

PLC = Path(pmcal.plc.__file__).parent
DOCS = Path(__file__).resolve().parent.parent / "docs"


def _enum(name: str) -> dict[int, str]:
    text = (PLC / "DUTs" / f"{name}.TcDUT").read_text(encoding="utf-8")
    return {int(v): k for k, v in re.findall(r"^\s*(\w+)\s*:=\s*(\d+)", text, re.M)}


def _table_rows(text: str) -> dict[int, str]:
    """``| value | NAME | ...`` rows of the markdown tables in ``text``."""
    return {int(v): n for v, n in re.findall(r"^\|\s*(\d+)\s*\|\s*([A-Z_]+)\s*\|", text, re.M)}


@pytest.mark.parametrize("doc", [DOCS / "commissioning.md", PLC / "README.md"], ids=lambda p: p.name)
def test_every_status_is_documented_with_its_value_and_name(doc):
    rows = _table_rows(doc.read_text(encoding="utf-8"))
    assert rows == _enum("E_CompTableStatus")


def test_every_manager_state_is_documented():
    text = (DOCS / "commissioning.md").read_text(encoding="utf-8")
    line = re.search(r"\*\*Manager state\*\*[^\n]*\n?[^\n]*", text)[0]
    listed = {int(v): n for v, n in re.findall(r"(\d+) ([A-Z_]+)", line)}
    assert listed == _enum("E_CompTableState")


def test_versions_and_sizes_named_in_the_docs_are_the_plcs():
    interface, fmt = plc_constant("INTERFACE_VERSION"), plc_constant("FORMAT_VERSION")
    bridge = (DOCS / "bridge.md").read_text(encoding="utf-8")
    assert f"interface version ({interface})" in bridge
    readme = (PLC / "README.md").read_text(encoding="utf-8")
    assert f"INTERFACE_VERSION {interface}, FORMAT_VERSION {fmt}" in readme
    commissioning = (DOCS / "commissioning.md").read_text(encoding="utf-8")
    for m in re.finditer(r"format (\d+)\b", commissioning):
        assert m[1] == fmt, m[0]
    assert f"FORMAT_VERSION ({fmt})" in readme
    from pmcal.bridge.plc_types import INTERFACE_VERSION
    assert str(INTERFACE_VERSION) == interface


def test_the_modbus_register_range_in_the_docs_is_the_areas():
    """ST_CompTableModbusArea: aWindow at register 384, WINDOW_LREALS LREALs of 4 registers each."""
    area = (PLC / "DUTs" / "ST_CompTableModbusArea.TcDUT").read_text(encoding="utf-8")
    window_at = int(re.search(r"aWindow\s*:.*//\s*(\d+)", area)[1])
    window = int(plc_constant("WINDOW_LREALS"))
    registers = window_at + 4 * window
    text = (DOCS / "commissioning.md").read_text(encoding="utf-8")
    assert f"registers 16#3000 … 16#{0x3000 + registers - 1:X} ({registers:,} registers".replace(",", " ") in text
    assert f"{2 * registers:,} bytes".replace(",", " ") in text
    assert f"window of {window} LREALs" in text


def test_the_commit_timings_in_the_docs_are_the_benchmarks():
    """The cycles a 100 x 100 commit takes, as benchmarks/plc_runtime_bench.py last measured them (its
    JSON), are the ones the docs give (and the seconds at a 1 ms task)."""
    import json

    bench = json.loads((DOCS.parent / "benchmarks" / "results" / "plc_runtime_bench.json").read_text())
    cycles = next(r["cycles"] for r in bench["commit"] if r["grid"] == "100x100")
    assert f"{cycles} cycles, {cycles / 1000:g} s of 1 ms cycles" in (DOCS / "commissioning.md").read_text()
    assert f"a 100x100 commit takes {cycles}\ncycles" in (PLC / "README.md").read_text(encoding="utf-8")
