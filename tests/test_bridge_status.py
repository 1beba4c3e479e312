"""``pmcal plc status`` / ``pmcal plc verify`` (issue 12, Deliver 3) against both mocks; --json parsed."""

from __future__ import annotations

import json

import pytest

from pmcal.bridge.simulator.ads_mock import AdsMockPlc
from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc
from pmcal.cli import main
from tests.bridge_fixtures import make_table, running


def _target(plc) -> list[str]:
    return ["--ads", plc.target] if plc.transport == "ads" else ["--modbus", plc.target]


@pytest.mark.parametrize("mock", [AdsMockPlc, ModbusMockPlc], ids=["ads", "modbus"])
def test_status_and_verify(mock, tmp_path, capsys):
    table = make_table(version=9, offset_deg=0.1)
    jp, _ = table.save(tmp_path / "t.json")
    other, _ = make_table(version=10).save(tmp_path / "u.json")
    with running(mock(lifetime_s=60.0)) as plc:
        assert main(["plc", "status", *_target(plc), "--json"]) == 0
        s = json.loads(capsys.readouterr().out)
        assert (s["active_version"], s["machine"], s["last_status"]) == (0, None, "NONE")
        assert main(["plc", "verify", str(jp), *_target(plc)]) == 4
        assert "not active" in capsys.readouterr().out
        plc.twin.seed(table)
        assert main(["plc", "status", *_target(plc), "--json"]) == 0
        s = json.loads(capsys.readouterr().out)
        assert (s["active_version"], s["active_crc32"], s["machine"], s["reference"], s["grid"]) == (
            9, f"0x{table.crc32():08X}", "ocpm_2dof", "nominal_ik", [37, 13])
        assert s["interface_version"] == 5 and s["state"] == "IDLE" and s["time"].endswith("Z")
        assert main(["plc", "verify", str(jp), *_target(plc), "--json"]) == 0
        v = json.loads(capsys.readouterr().out)
        assert v["active"] is True and v["version"] == 9
        assert main(["plc", "verify", str(other), *_target(plc)]) == 4
        assert "runs version 9" in capsys.readouterr().out
        assert plc.writes == 0                           # status and verify only read


def test_local_netid_is_checked(capsys):
    assert main(["plc", "status", "--ads", "1.2.3.4.1.1@127.0.0.1:1", "--local-netid", "1.2.3"]) == 2
    assert "--local-netid" in capsys.readouterr().err
