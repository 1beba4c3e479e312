"""Integrity and order of a push (issue 12): refused before connecting, local checks before the first
write, the real reason when motion blocks the swap, and ``--wait-motion``.

References: a plain TCP listener (socket module) to see whether any connection was made at all; the
PLC twin's state read directly (not through the bridge).
"""

from __future__ import annotations

import json
import socket
import threading
import time

import pytest

from pmcal.bridge.simulator.ads_mock import AdsMockPlc
from pmcal.bridge.errors import AckTimeout, Rejected
from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc
from pmcal.bridge.simulator.plc_runtime import PlcTwin
from pmcal.bridge.plc_types import COMMIT_TIMEOUT_S, State, Status, done_value
from pmcal.bridge.transfer import PushOptions, push
from pmcal.cli import main
from tests.bridge_fixtures import BIG_TABLE_ACK_S, BIG_TABLE_TIMEOUT_S, ads_link, make_table, modbus_link, running


def _listener():
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.bind(("127.0.0.1", 0))
    srv.listen(4)
    srv.setblocking(False)
    return srv


def _accepted(srv) -> bool:
    try:
        conn, _ = srv.accept()
    except BlockingIOError:
        return False
    conn.close()
    return True


@pytest.mark.parametrize("drop", ["crc32", "sha256", "both"])
@pytest.mark.parametrize("transport", ["ads", "modbus"])
def test_table_without_checksums_is_refused_before_connecting(tmp_path, capsys, drop, transport):
    jp, _ = make_table(version=5).save(tmp_path / "comp.json")
    doc = json.loads(jp.read_text())
    for key in (("crc32", "sha256") if drop == "both" else (drop,)):
        del doc[key]
    jp.write_text(json.dumps(doc))
    srv = _listener()
    try:
        port = srv.getsockname()[1]
        target = ["--ads", f"127.0.0.1.1.1@127.0.0.1:{port}"] if transport == "ads" else [
            "--modbus", f"127.0.0.1:{port}"]
        assert main(["push", str(jp), *target, "--timeout", "0.3"]) == 2
        time.sleep(0.05)
        assert not _accepted(srv)                        # no connection was even attempted
    finally:
        srv.close()
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "checksum" in err and str(jp) in err
    assert not (tmp_path / "bridge_audit.log").exists()


def test_table_whose_data_do_not_match_the_checksum_is_refused_before_connecting(tmp_path, capsys):
    jp, _ = make_table(version=5).save(tmp_path / "comp.json")
    doc = json.loads(jp.read_text())
    doc["values"][1][1][1] += 1e-6
    jp.write_text(json.dumps(doc))
    srv = _listener()
    try:
        assert main(["push", str(jp), "--modbus", f"127.0.0.1:{srv.getsockname()[1]}"]) == 2
        assert not _accepted(srv)
    finally:
        srv.close()
    assert "CRC mismatch" in capsys.readouterr().err


@pytest.mark.parametrize("option", ["--audit", "--json"])
def test_unwritable_local_output_is_found_before_the_first_write(tmp_path, capsys, option):
    jp, _ = make_table(version=2).save(tmp_path / "comp.json")
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("a file where a folder is expected\n")
    with running(AdsMockPlc(lifetime_s=60.0)) as plc:
        plc.twin.seed(make_table(version=1))
        code = main(["push", str(jp), "--ads", plc.target, option, str(blocker / "out.log")])
        assert code == 2
        assert plc.writes == 0 and plc.requests == 0
        assert plc.twin.state.active_version == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and option in err and "nothing was sent" in err


@pytest.mark.parametrize("link", [ads_link, modbus_link], ids=["ads", "modbus"])
def test_moving_machine_is_reported_as_wait_motion(link):
    mock = AdsMockPlc if link is ads_link else ModbusMockPlc
    with running(mock(lifetime_s=60.0)) as plc:
        plc.twin.seed(make_table(version=1))
        plc.twin.motion_idle = False
        with pytest.raises(AckTimeout, match=r"waits for the machine to stop \(WAIT_MOTION") as exc:
            push(link(plc), make_table(version=2), PushOptions(ack_timeout_s=0.3))
        assert "active version stays 1" in str(exc.value) and "--wait-motion" in str(exc.value)
        st = plc.twin.state
        assert (st.active_version, st.status, st.state) == (1, Status.WITHDRAWN, State.IDLE)


def test_swap_timeout_of_the_plc_reaches_the_user():
    with running(AdsMockPlc(PlcTwin(commit_timeout_s=0.2), lifetime_s=60.0)) as plc:
        plc.twin.seed(make_table(version=1))
        plc.twin.motion_idle = False
        with pytest.raises(Rejected, match="SWAP_TIMEOUT") as exc:
            push(ads_link(plc), make_table(version=2), PushOptions(ack_timeout_s=2.0))
        assert "--wait-motion" in str(exc.value) and "active version stays 1" in str(exc.value)
        assert plc.twin.state.active_version == 1


def test_wait_motion_keeps_the_commit_up_until_the_machine_stops():
    new = make_table(version=2, offset_deg=0.1)
    with running(AdsMockPlc(PlcTwin(commit_timeout_s=0.2), lifetime_s=60.0)) as plc:
        plc.twin.seed(make_table(version=1))
        plc.twin.motion_idle = False
        stopper = threading.Timer(0.8, lambda: setattr(plc.twin, "motion_idle", True))   # the move ends
        stopper.start()
        try:
            rep = push(ads_link(plc), new, PushOptions(ack_timeout_s=2.0, wait_motion_s=5.0))
        finally:
            stopper.cancel()
        assert (rep.result, rep.active_version) == ("ok", 2)
        assert plc.twin.active_table()[1].tobytes() == new.values.tobytes()


def test_bridge_ack_timeout_is_longer_than_the_plc_commit_timeout():
    """Aligned defaults: the PLC's verdict (SWAP_TIMEOUT) always arrives before the bridge gives up."""
    assert PushOptions().ack_timeout_s > COMMIT_TIMEOUT_S == PlcTwin().commit_timeout_s
    from tests.test_bridge_plc import DECL
    assert "COMMIT_TIMEOUT    : TIME := T#4S" in DECL["GVL_CompTableParam"]


# ---- concurrent pushes: the PLC arbitrates the staging area -----------------------------------

@pytest.mark.parametrize("link", [ads_link, modbus_link], ids=["ads", "modbus"])
def test_second_client_is_told_another_client_is_staging(link):
    from pmcal.bridge.errors import StagingBusy

    mock = AdsMockPlc if link is ads_link else ModbusMockPlc
    with running(mock(lifetime_s=60.0)) as plc:
        plc.twin.seed(make_table(version=1))
        other = link(plc)
        with other:
            other.write_claim(0x92345679)                  # a client that owns the staging area
            time.sleep(0.02)
            assert plc.twin.state.staging_owner == 0x92345679
            with pytest.raises(StagingBusy, match="another client is staging") as exc:
                push(link(plc), make_table(version=2), PushOptions(ack_timeout_s=1.0, claim_timeout_s=0.3))
            assert "nothing committed" in str(exc.value)
            assert plc.twin.state.active_version == 1
            assert plc.twin.state.staging_owner == 0x92345679   # the loser did not take it over
            other.write_claim(done_value(0x92345679))      # the owner finishes
        time.sleep(0.02)
        rep = push(link(plc), make_table(version=2), PushOptions(ack_timeout_s=1.0))
        time.sleep(0.02)
        assert rep.result == "ok" and plc.twin.state.staging_owner == 0     # released after the push


@pytest.mark.parametrize("transport", ["ads", "modbus"])
def test_concurrent_pushes_one_wins_the_other_hears_why(transport):
    from pmcal.bridge.errors import StagingBusy

    mock = AdsMockPlc if transport == "ads" else ModbusMockPlc
    link = ads_link if transport == "ads" else modbus_link
    tables = [make_table(version=v, n_phi=100, n_theta=100, offset_deg=0.01 * v) for v in (2, 3)]
    with running(mock(lifetime_s=60.0)) as plc:
        plc.twin.seed(make_table(version=1, n_phi=100, n_theta=100))
        results = [None, None]

        def run(k):
            try:
                results[k] = push(link(plc, timeout_s=BIG_TABLE_TIMEOUT_S), tables[k],
                                  PushOptions(ack_timeout_s=BIG_TABLE_ACK_S)).result
            except StagingBusy as exc:
                results[k] = str(exc)
            except Exception as exc:                     # noqa: BLE001 - reported in the assertion below
                results[k] = f"{type(exc).__name__}: {exc}"

        threads = [threading.Thread(target=run, args=(k,)) for k in (0, 1)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(30)
        # never a byte-offset read-back failure: each push either made its table active or was told why
        for r in results:
            assert r == "ok" or "another client is staging" in r or "not newer" in r, results
        assert "ok" in results
        active = plc.twin.state.active_version
        assert plc.twin.active_table()[1].tobytes() == tables[active - 2].values.tobytes()
