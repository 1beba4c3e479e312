"""The README's command-line walkthrough runs as written, top to bottom, in an empty folder.

The blocks are parsed from README.md (the first two ``sh`` blocks after "## Command line"), so the README
cannot drift from the code. The first (the walkthrough) runs in CI; the second (the whole demos, minutes)
is marked slow.
"""

import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def command_blocks() -> list[str]:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    section = text[text.index("## Command line"):]
    section = section[:section.index("\n## ", 1)]
    return re.findall(r"```sh\n(.*?)```", section, flags=re.S)


def run_block(block: str, cwd: Path, timeout: float) -> subprocess.CompletedProcess:
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
               MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    proc = subprocess.Popen(["bash", "-euo", "pipefail", "-c", block], cwd=cwd, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    finally:
        try:                                     # the background mock PLC of the walkthrough
            os.killpg(proc.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def test_readme_has_the_walkthrough_blocks():
    blocks = command_blocks()
    assert len(blocks) == 2
    assert "pmcal targets" in blocks[0] and "mock-plc" in blocks[0] and "push" in blocks[0]


def test_readme_walkthrough_runs_verbatim(tmp_path):
    res = run_block(command_blocks()[0], tmp_path, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    for name in ("targets.csv", "m.csv", "pm.png", "params.json", "paper.json", "setpoints.csv",
                 "comp_table.json", "diagnosis.json", "diag/index.html", "t.csv", "params_t.json", "planar.csv",
                 "planar.json", "calibrated.xml", "calibrated.toml", "history.html"):
        assert (tmp_path / name).is_file(), name
    assert "pmcal: wrote setpoints.csv" in res.stdout
    assert "dry_run" in res.stdout
    assert "Traceback" not in res.stderr
    # piped, every result is on stdout; the README's campaigns draw no warning (the tracker step's 48 poses)
    assert res.stdout.count("parameter directions determined") == 4   # identify: full, paper, tracker, history
    assert "no missing effect: the model explains the data to the noise level" in res.stdout
    assert "pmcal: wrote bridge_audit.log" in res.stdout
    assert "pmcal: warning" not in res.stderr, res.stderr


@pytest.mark.slow
def test_readme_demos_run_verbatim(tmp_path):
    res = run_block(command_blocks()[1], tmp_path, timeout=3600)
    assert res.returncode == 0, res.stderr[-2000:]
    # piped, each demo prints its result: the improvement, the hidden effect and the diagnosis
    assert "pmcal demo: pmcal-demo/report.html" in res.stdout and " -> " in res.stdout
    assert "hidden: " in res.stdout and "; diagnosed: " in res.stdout
    assert "planar_2dof demo: " in res.stdout
    for name in ("pmcal-demo", "pmcal-demo-hidden", "pmcal-demo-planar"):
        assert (tmp_path / name / ".pmcal-output").is_file(), name
