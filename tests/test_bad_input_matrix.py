"""The bad-input matrix of issue 33 (tests/bad_inputs/cases.toml, run by benchmarks/bad_input_matrix.py):
its fast subset here, every case run as a real ``pmcal`` subprocess in a fresh copy of the fixture under a
memory limit; every one must come out ``ok`` (no data lost, no silent wrong success, no traceback, no hang
or memory blow-up, no staging leftover, the one line that names the cause). The whole matrix: the
benchmark (about 20 minutes on 2 cores).
"""

from __future__ import annotations

import pytest

from benchmarks.bad_input_matrix import MACHINES, build_fixture, fixture_kinds, load_cases, run

CASES = load_cases()


def test_the_matrix_covers_every_command_and_machine_kind():
    assert len(CASES) >= 300
    for kind in MACHINES:
        assert sum(c.machine == kind for c in CASES) >= 40, kind
    words = {w for c in CASES for w in c.argv}
    for command in ("demo", "identify", "compensate", "evaluate", "diagnose", "targets", "twin", "measure", "render",
                    "plan", "push", "plc", "mock-plc", "loop", "import", "export-model", "history"):
        assert command in words, command
    assert {c.expect for c in CASES} == {"ok", "refused", "failed"}


@pytest.fixture(scope="module")
def fixture(tmp_path_factory):
    fast = [c for c in CASES if c.fast]
    return build_fixture(tmp_path_factory.mktemp("matrix"), fixture_kinds(fast)), fast


def test_the_fast_subset_is_handled_well(fixture):
    root, fast = fixture
    assert len(fast) >= 20
    results = run(fast, root, timeout=120.0, memory_gb=4.0)
    bad = [f"{r.id}: {r.klass} (exit {r.status}): {r.stderr[-300:]}" for r in results if r.klass != "ok"]
    assert not bad, "\n".join(bad)
