"""A push stopped by SIGTERM says what became of it and where to look; ``pmcal plc status`` says it in words
(issue 33). The mock PLC is the strict Modbus mock (the shipped ST, cycle by cycle), in this process; the
push is a real ``pmcal push`` subprocess held by a delay fault in the middle of staging, then terminated.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

from pmcal.bridge.simulator.faults import Fault, FaultPlan, Kind, Point
from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc
from pmcal.cli import main
from tests.bridge_fixtures import ROOT_DIR, make_table, running


def test_a_terminated_push_names_its_fate_and_status_says_it_in_words(tmp_path, capsys):
    first, second = make_table(version=5), make_table(version=6, offset_deg=0.01)
    first.save(tmp_path / "v5.json")
    second.save(tmp_path / "v6.json")
    faults = FaultPlan()
    with running(ModbusMockPlc(lifetime_s=120.0, faults=faults)) as plc:
        target = f"{plc.host}:{plc.port}"
        assert main(["push", str(tmp_path / "v5.json"), "--modbus", target, "--no-audit"]) == 0
        faults.arm(Fault(Kind.DELAY, Point.MID_STAGE, times=1, delay_s=30.0))
        proc = subprocess.Popen([sys.executable, "-m", "pmcal.cli", "push", str(tmp_path / "v6.json"), "--modbus",
                                 target, "--no-audit", "--timeout", "60"], cwd=ROOT_DIR, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True, env=dict(os.environ))
        for _ in range(1200):                       # until the delay fault holds the push mid-staging (<= 120 s)
            if faults.fired or proc.poll() is not None:
                break
            time.sleep(0.1)
        assert faults.fired and proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 143, err
        lines = err.strip().splitlines()
        assert len(lines) == 1 and "push of" in lines[0] and "v6 terminated" in lines[0], err
        assert f"'pmcal plc status --modbus {target}'" in lines[0]
        capsys.readouterr()
        assert main(["plc", "status", "--modbus", target]) == 0
        words = capsys.readouterr().out.splitlines()[-1]
    # the push stopped before its commit: v5 still runs, v6 did not land
    assert words.startswith("The PLC runs table v5 "), words
    assert "a push of that version landed; any other did not" in words, words


def test_a_busy_port_for_the_mock_plc_is_one_line(capsys):
    import socket

    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        for transport in ("--modbus", "--ads"):
            capsys.readouterr()
            assert main(["mock-plc", transport, "--port", str(port), "--seconds", "1"]) == 2
            err = capsys.readouterr().err.strip()
            assert err == (f"pmcal: error: field '--port': cannot listen on 127.0.0.1:{port}: Address already in use "
                           "(another program, or another mock PLC, uses it: choose another port or 0 for a free one)")
