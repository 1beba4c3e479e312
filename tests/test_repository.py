"""The repository's promises: README set-up commands, CI entry point, pinned versions, layout."""

import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def readme_commands():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert lines[0].startswith("```")
    block = lines[1:lines.index("```", 1)]
    return [l for l in block if l.strip()]


def test_readme_opens_with_exactly_two_setup_commands():
    cmds = readme_commands()
    assert len(cmds) == 2
    assert cmds[0].endswith("pmcal demo")
    assert "pytest" in cmds[1]


def test_ci_runs_the_readme_test_command_verbatim():
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert readme_commands()[1] in ci


def test_checked_versions_are_pinned():
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    pins = {d.split(">=")[0].split("<")[0].split("=")[0]: d for d in deps}
    assert ">=4.0.0,<4.1" in pins["mujoco"]
    assert ">=3.6.0,<3.7" in pins["pyads"]
    assert ">=3.16.1,<3.17" in pins["pymodbus"]


def test_top_level_layout():
    for name in ("mjcf", "twin", "calib", "bridge", "tests", "pyproject.toml"):
        assert (ROOT / name).exists(), name
    for machine in ("ocpm_2dof", "delta_3dof", "hexapod_6dof"):
        folder = ROOT / "mjcf" / machine
        for f in (f"{machine}.xml", "scene.xml", "README.md", "machine.toml"):
            assert (folder / f).exists(), f


def test_atomic_write_leaves_readable_files(tmp_path):
    """Outputs get the permissions of an ordinary new file (mkstemp alone would give 0600)."""
    import os

    from pmcal.fileio import atomic_directory, atomic_write

    mask = os.umask(0o022)
    try:
        with atomic_write(tmp_path / "a.csv") as fh:
            fh.write("x\n")
        with atomic_directory(tmp_path / "report") as d:
            (d / "index.html").write_text("<html></html>")
    finally:
        os.umask(mask)
    assert (tmp_path / "a.csv").stat().st_mode & 0o777 == 0o644
    assert (tmp_path / "report").stat().st_mode & 0o777 == 0o755


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    from pmcal.fileio import atomic_write

    target = tmp_path / "out.csv"
    try:
        with atomic_write(target) as fh:
            fh.write("half")
            raise RuntimeError("boom")
    except RuntimeError:
        pass
    assert list(tmp_path.iterdir()) == []
