"""``pmcal push`` and ``pmcal mock-plc``: exit statuses, one-line errors, audit log, nothing half-done."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from pmcal.bridge.simulator.ads_mock import AdsMockPlc
from pmcal.bridge.simulator.faults import Fault, Kind, Point
from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc
from pmcal.cli import main
from tests.bridge_fixtures import ROOT_DIR, make_table, running


def _target_args(plc) -> list[str]:
    return ["--ads", plc.target] if plc.transport == "ads" else ["--modbus", plc.target]


@pytest.mark.parametrize("mock", [AdsMockPlc, ModbusMockPlc], ids=["ads", "modbus"])
def test_push_succeeds_writes_audit_and_report(mock, tmp_path, capsys):
    table = make_table(version=3)
    jp, _ = table.save(tmp_path / "comp.json")
    with running(mock(lifetime_s=60.0)) as plc:
        code = main(["push", str(jp), *_target_args(plc), "--timeout", "0.5", "--json", str(tmp_path / "r.json")])
        out = capsys.readouterr()
        assert code == 0, out.err
        assert out.out.startswith("ok: ") and "version 3 active (was 0)" in out.out
        assert plc.twin.active_table()[1].tobytes() == table.values.tobytes()
    audit = [json.loads(l) for l in (tmp_path / "bridge_audit.log").read_text().splitlines()]
    report = json.loads((tmp_path / "r.json").read_text())
    assert len(audit) == 1 and audit[0]["sha256_sent"] == report["sha256_sent"] and report["result"] == "ok"


def test_dry_run_and_csv_input(tmp_path, capsys):
    _, cp = make_table(version=1).save(tmp_path / "comp.json")
    with running(AdsMockPlc(lifetime_s=60.0)) as plc:
        assert main(["push", str(cp), "--ads", plc.target, "--dry-run", "--no-audit"]) == 0
        assert plc.writes == 0
    assert "dry run: would stage" in capsys.readouterr().out
    assert not (tmp_path / "bridge_audit.log").exists()


def test_bad_table_exits_2_with_file_row_field_and_writes_nothing(tmp_path, capsys):
    table = make_table(version=2, n_phi=5, n_theta=4)
    table.values[2, 1, 1] = np.nan
    cp = tmp_path / "comp.csv"
    table.to_csv(cp)
    with running(ModbusMockPlc(lifetime_s=60.0)) as plc:
        assert main(["push", str(cp), "--modbus", plc.target]) == 2
        assert plc.requests == 0
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and f"{cp}, row 10, field 'm2_deg'" in err and "not a finite number" in err


def test_stale_version_exits_2(tmp_path, capsys):
    jp, _ = make_table(version=4).save(tmp_path / "comp.json")
    with running(AdsMockPlc(lifetime_s=60.0)) as plc:
        plc.twin.seed(make_table(version=4, offset_deg=1.0))
        assert main(["push", str(jp), "--ads", plc.target]) == 2
        assert plc.writes == 0
    assert "not newer than the active version 4" in capsys.readouterr().err
    assert json.loads((tmp_path / "bridge_audit.log").read_text())["result"] == "refused"


def test_rejection_exits_3_and_link_failure_exits_1(tmp_path, capsys):
    jp, _ = make_table(version=1).save(tmp_path / "comp.json")
    with running(AdsMockPlc(lifetime_s=60.0)) as plc:
        plc.faults.arm(Fault(Kind.CORRUPT, Point.COMMIT))
        assert main(["push", str(jp), "--ads", plc.target]) == 3
        target = plc.target
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "PLC rejected version 1: CRC_MISMATCH" in err
    assert main(["push", str(jp), "--ads", target, "--attempts", "1", "--timeout", "0.3"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("pmcal: failed: push of") and "nothing committed" in err


@pytest.mark.parametrize("args, field", [(["--ads", "1.2.3@x"], "--ads"), (["--modbus", "h:99999"], "--modbus"),
                                         (["--modbus", "h", "--attempts", "0"], "--attempts"),
                                         (["--modbus", "127.0.0.1:502:3"], "--modbus"),
                                         (["--ads", "1.2.3.4.1.1@127.0.0.1:1", "--ams-port", "70000"], "--ams-port")])
def test_bad_arguments_exit_2(tmp_path, capsys, args, field):
    jp, _ = make_table(version=1).save(tmp_path / "comp.json")
    assert main(["push", str(jp), *args]) == 2
    assert f"field '{field}'" in capsys.readouterr().err


@pytest.mark.parametrize("version", [-1, 2**40])
def test_table_version_outside_udint_is_bad_input(tmp_path, capsys, version):
    """A version the PLC header cannot hold is named (was struct.error, exit 1), before any connection."""
    jp, cp = make_table(version=1).save(tmp_path / "comp.json")
    doc = json.loads(jp.read_text())
    jp.write_text(json.dumps(dict(doc, table_version=version)))
    cp.write_text(cp.read_text().replace("# table_version=1\n", f"# table_version={version}\n"))
    for path in (jp, cp):
        assert main(["push", str(path), "--modbus", "127.0.0.1:1", "--no-audit"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and path.name in err[0] and "field 'table_version'" in err[0], err


def test_mock_plc_command_serves_a_push(tmp_path):
    good, new = make_table(version=1), make_table(version=2, offset_deg=0.1)
    gp, _ = good.save(tmp_path / "good.json")
    np_, _ = new.save(tmp_path / "new.json")
    proc = subprocess.Popen([sys.executable, "-m", "pmcal.cli", "mock-plc", "--modbus", "--seconds", "20",
                             "--table", str(gp)], cwd=ROOT_DIR, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        first = proc.stdout.readline()
        assert first.startswith("mock PLC (modbus) at 127.0.0.1:"), proc.stderr.read() if proc.poll() else first
        target = first.split(" at ")[1].split()[0]
        assert main(["push", str(np_), "--modbus", target, "--no-audit"]) == 0
        assert main(["push", str(gp), "--modbus", target, "--no-audit"]) == 2        # stale now
    finally:
        proc.terminate()
        try:
            out, _ = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
    assert "active version 2" in out


def test_a_key_given_twice_in_the_table_json_is_refused(tmp_path, capsys):
    """The last of two ``table_version`` keys won without a word (json keeps the last); the CRC does not see it
    when the last one is the true one. Refused naming the file and the key, before any connection."""
    jp, _ = make_table(version=1).save(tmp_path / "comp.json")
    jp.write_text(jp.read_text().replace('"table_version": 1,', '"table_version": 5,\n "table_version": 1,', 1))
    with running(ModbusMockPlc(lifetime_s=60.0)) as plc:
        assert main(["push", str(jp), "--modbus", plc.target, "--json", str(tmp_path / "r.json")]) == 2
        assert plc.requests == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{jp}: duplicate key 'table_version'" in err[0], err
    assert not (tmp_path / "r.json").exists() and not (tmp_path / "bridge_audit.log").exists()


def test_ads_host_without_an_ads_router_names_host_ports_and_what_to_check(tmp_path, capsys):
    """An unreachable host (here a closed TCP port) made AdsLib answer 'ADS error 6' at the connection, which
    the line blamed on a stopped PLC runtime: it now names the host, TCP port, AMS NetID and AMS port and says
    what to check (reachability, the route on the PLC, the NetID, --ams-port 851). A connection failure:
    exit 1, within the push's time bound."""
    import socket
    import time

    with socket.socket() as s:                 # a port nothing listens on: the connection is refused
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    jp, _ = make_table(version=1).save(tmp_path / "comp.json")
    t0 = time.monotonic()
    assert main(["push", str(jp), "--ads", f"1.2.3.4.1.1@127.0.0.1:{port}", "--no-audit"]) == 1
    assert time.monotonic() - t0 < 5.0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert f"no ADS connection to 127.0.0.1 (TCP port {port}, AMS NetID 1.2.3.4.1.1, AMS port 851)" in err[0], err
    assert "route for this client's AMS NetID" in err[0] and "851 for the first TwinCAT 3 PLC runtime" in err[0]
    assert "nothing committed" in err[0]
