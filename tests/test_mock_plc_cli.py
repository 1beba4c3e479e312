"""``pmcal mock-plc --power-cut-after S``: the mock PLC (a subprocess) loses power once, its clients lose
their connections, it is unreachable for ``--restart-s``, then it runs again on the same address with
the acknowledged table active (issue 21, Deliver 6). Checked with the project's link and a plain
pyads client; the options are validated up front.
"""

from __future__ import annotations

import os
import queue
import subprocess
import sys
import threading

import pyads
import pytest
from pyads import constants

from pmcal.bridge.ads import AdsLink
from pmcal.bridge.ads_map import AdsTarget
from pmcal.bridge.errors import LinkError
from pmcal.bridge.transfer import PushOptions, push
from pmcal.cli import main as cli
from tests.bridge_fixtures import ROOT_DIR, TIMEOUT_S, make_table


def _lines(proc) -> queue.Queue:
    q: queue.Queue = queue.Queue()

    def pump() -> None:
        for line in proc.stdout:
            q.put(line.rstrip("\n"))
        q.put(None)
    threading.Thread(target=pump, daemon=True).start()
    return q


def _expect(q: queue.Queue, text: str, timeout_s: float = 30.0) -> str:
    while True:
        line = q.get(timeout=timeout_s)
        if line is None:
            raise AssertionError(f"mock-plc ended before printing {text!r}")
        if text in line:
            return line


def test_power_cut_drops_clients_then_the_plc_comes_back_with_the_acknowledged_table():
    cmd = [sys.executable, "-m", "pmcal.cli", "mock-plc", "--ads", "--seconds", "60", "--power-cut-after", "3",
           "--restart-s", "1.5"]
    proc = subprocess.Popen(cmd, cwd=ROOT_DIR, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, MUJOCO_GL="egl"))
    try:
        q = _lines(proc)
        target = AdsTarget.parse(_expect(q, "mock PLC (ads) at").split(" at ")[1].split(" for ")[0])
        table = make_table(version=3)
        assert push(AdsLink(target, timeout_s=TIMEOUT_S), table).result == "ok"
        conn = pyads.Connection(target.netid, 851, f"{target.host}:{target.tcp_port}")
        conn.open()
        conn.set_timeout(300)
        assert conn.read_state()[0] == constants.ADSSTATE_RUN
        _expect(q, "power cut")
        with pytest.raises(LinkError):                       # the PLC is away
            push(AdsLink(target, timeout_s=TIMEOUT_S), make_table(version=4), PushOptions(attempts=1))
        with pytest.raises(pyads.ADSError):                  # the old connection is gone
            conn.read_state()
        conn.close()
        back = _expect(q, "running again")
        assert "active version 3" in back                    # acknowledged before the cut: kept
        assert push(AdsLink(target, timeout_s=TIMEOUT_S), make_table(version=4)).result == "ok"
    finally:
        proc.terminate()
        proc.communicate(timeout=10)


@pytest.mark.parametrize("argv, field", [
    (["--ads", "--power-cut-after", "0"], "--power-cut-after"),
    (["--ads", "--power-cut-after", "700"], "--power-cut-after"),
    (["--ads", "--restart-s", "-1"], "--restart-s"),
    (["--modbus", "--route", "1.2.3.4.1.1"], "--route"),
    (["--ads", "--route", "1.2.3.4"], "--route"),
    (["--ads", "--staging-lease", "0"], "--staging-lease"),
])
def test_mock_plc_options_are_checked_up_front(argv, field, capsys):
    assert cli(["mock-plc", *argv]) == 2
    err = capsys.readouterr().err
    assert field in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
