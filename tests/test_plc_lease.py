"""No lock-out: a client that dies at any point of a push blocks the next push for at most the staging
lease; a client that comes back after its lease cannot commit over the new owner (fencing token); an
operator can free the area at once (``pmcal plc unlock``); after a restart commits are answered
PLC_STARTING until the persistent table is re-checked, and the client retries.

Everything runs on the shipped ST (plc/, interpreted cycle by cycle) behind the real ADS and Modbus mock
servers, with the lease shortened to LEASE_S (the GVL constant; FB_CompTableManager.tStagingLease).
The dead client is driven with the bridge's own link primitives and then abandoned mid-protocol, as a
killed ``pmcal push`` would leave the PLC.
"""

from __future__ import annotations

import json

import pytest

from pmcal.bridge.simulator.ads_mock import AdsMockPlc
from pmcal.bridge.errors import StagingBusy
from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc
from pmcal.bridge.simulator.plc_runtime import PlcTwin
from pmcal.bridge.plc_types import Header, State, Status, done_value, shadow_rows
from pmcal.bridge.transfer import PushOptions, push
from tests.bridge_fixtures import ads_link, make_table, modbus_link, running, wait_state

LEASE_S = 1.0
#: what a push may wait for the staging area here: the shortened lease plus the margin of the default
OPTIONS = PushOptions(claim_timeout_s=LEASE_S + 5.0, ack_timeout_s=4.5)
DEAD = 0x8DEAD001
MOCKS = [pytest.param(AdsMockPlc, ads_link, id="ads"), pytest.param(ModbusMockPlc, modbus_link, id="modbus")]


def _plc(mock):
    plc = mock(PlcTwin(staging_lease_s=LEASE_S), lifetime_s=120.0)
    return plc


def _dead_push(plc, link, stop_at: str, version: int = 2) -> None:
    """A push that dies at ``stop_at``: 'claimed', 'mid_stage', 'committed' or 'acknowledged'."""
    table = make_table(version=version, offset_deg=0.2)
    with link(plc) as ln:
        ln.write_claim(DEAD)
        wait_state(plc, lambda s: s.staging_owner == DEAD)
        if stop_at == "claimed":
            return
        rows = shadow_rows(table)
        ln.write_symbol("shadow_header", Header.of(table).pack())
        if stop_at == "mid_stage":
            return                                        # header staged, data never sent
        ln.stage(Header.of(table).pack(), rows)
        ln.write_commit(DEAD)
        if stop_at == "committed":
            return                                        # killed right after the commit
        wait_state(plc, lambda s: s.ack_token == DEAD and s.state == State.IDLE)
        # 'acknowledged': killed while reading the acknowledgement, nothing released


@pytest.mark.parametrize("stop_at", ["claimed", "mid_stage", "committed", "acknowledged"])
@pytest.mark.parametrize("mock, link", MOCKS)
def test_a_dead_pusher_blocks_the_next_push_for_at_most_the_lease(mock, link, stop_at):
    with running(_plc(mock)) as plc:
        plc.twin.seed(make_table(version=1))
        _dead_push(plc, link, stop_at)
        new = make_table(version=3)
        rep = push(link(plc), new, OPTIONS)
        assert rep.result == "ok" and rep.active_version == 3
        st = plc.twin.state
        assert (st.active_version, st.active_crc, st.staging_owner, st.ack_token) == (3, new.crc32(), 0, 0)
        assert plc.twin.active_table()[1].tobytes() == new.values.tobytes()
        assert not plc.twin.stopped


@pytest.mark.parametrize("mock, link", MOCKS)
def test_a_client_back_after_its_lease_cannot_commit_over_the_new_owner(mock, link):
    with running(_plc(mock)) as plc:
        plc.twin.seed(make_table(version=1))
        _dead_push(plc, link, "mid_stage", version=2)     # frozen with the area ...
        stale = make_table(version=2, offset_deg=0.2)
        with link(plc) as other:                           # ... another client takes it after the lease
            other.write_claim(0x8000B0B1)
            st = wait_state(plc, lambda s: s.staging_owner == 0x8000B0B1)
            with link(plc) as back:                        # the frozen client wakes up and commits
                back.stage(Header.of(stale).pack(), shadow_rows(stale))
                back.write_commit(DEAD)
                import time
                time.sleep(0.1)
                st = plc.twin.state
                assert (st.active_version, st.ack_token, st.staging_owner) == (1, 0, 0x8000B0B1)
            other.write_claim(done_value(0x8000B0B1))
        # the stale client's bridge notices it lost the area and commits nothing
        assert push(link(plc), make_table(version=4), OPTIONS).result == "ok"
        assert plc.twin.state.active_version == 4


@pytest.mark.parametrize("mock, link", MOCKS)
def test_a_live_owner_is_not_overtaken_before_its_lease(mock, link):
    with running(_plc(mock)) as plc:
        plc.twin.seed(make_table(version=1))
        _dead_push(plc, link, "claimed")
        with pytest.raises(StagingBusy, match="another client is staging"):
            push(link(plc), make_table(version=2), PushOptions(claim_timeout_s=0.3))
        assert plc.twin.state.staging_owner == DEAD


def test_unlock_takes_the_area_over_after_the_lease_and_is_audited(tmp_path, capsys):
    from pmcal.cli import main

    with running(_plc(AdsMockPlc)) as plc:
        plc.twin.seed(make_table(version=1))
        _dead_push(plc, ads_link, "committed")
        audit = tmp_path / "audit.log"
        code = main(["plc", "unlock", "--ads", plc.target, "--yes", "--audit", str(audit), "--wait", "5"])
        assert code == 0 and "unlocked" in capsys.readouterr().out
        assert plc.twin.state.staging_owner == 0
        line = json.loads(audit.read_text().splitlines()[-1])
        assert (line["event"], line["owner"], line["result"]) == ("unlock", f"0x{DEAD:08X}", "ok")
        rep = push(ads_link(plc), make_table(version=3), PushOptions(claim_timeout_s=1.0))
        assert rep.result == "ok"


@pytest.mark.parametrize("mock, link", MOCKS)
def test_unlock_cannot_break_a_live_owner(tmp_path, capsys, mock, link):
    """An owner that keeps showing activity (here: it commits, is answered, clears and commits again)
    keeps the staging area: unlock waits longer than the lease and changes nothing."""
    import threading
    import time

    from pmcal.cli import main

    with running(_plc(mock)) as plc:
        plc.twin.seed(make_table(version=1))
        stop = threading.Event()
        with link(plc) as ln:
            ln.write_claim(DEAD)
            wait_state(plc, lambda s: s.staging_owner == DEAD)

            def live_owner():                              # a commit of a stale version every ~0.3 s
                stale = make_table(version=1, offset_deg=0.1)
                ln.stage(Header.of(stale).pack(), shadow_rows(stale))
                while not stop.is_set():
                    ln.write_commit(DEAD)
                    time.sleep(0.15)
                    ln.write_commit(done_value(DEAD))
                    time.sleep(0.15)
            owner = threading.Thread(target=live_owner)
            owner.start()
            try:
                target = ["--ads", plc.target] if mock is AdsMockPlc else ["--modbus", f"{plc.host}:{plc.port}"]
                code = main(["plc", "unlock", *target, "--yes", "--audit", str(tmp_path / "a.log"),
                             "--wait", str(2.5 * LEASE_S)])
            finally:
                stop.set()
                owner.join()
        assert code == 1 and "kept the staging area" in capsys.readouterr().err
        assert plc.twin.state.staging_owner == DEAD and plc.twin.state.active_version == 1


def test_a_commit_during_the_start_up_check_is_answered_plc_starting():
    table = make_table(version=5, n_phi=100, n_theta=100)
    twin = PlcTwin()
    twin.seed(table)
    twin.restart()                                         # the start-up check takes ~740 cycles
    twin.write_symbol("staging_claim", DEAD.to_bytes(4, "little"))
    twin.cycle()
    assert (twin.state.state, twin.state.staging_owner) == (State.STARTING, DEAD)
    new = make_table(version=6)
    twin.write_symbol("shadow_header", Header.of(new).pack())
    twin.write_shadow_bytes(0, shadow_rows(new))
    twin.write_symbol("commit", DEAD.to_bytes(4, "little"))
    twin.cycle()
    st = twin.state
    assert (st.status, st.ack_token, st.state, st.active_version) == (Status.PLC_STARTING, DEAD, State.STARTING, 5)
    # the check of the persistent table went on in its own instance; the commit did not disturb it
    for _ in range(5_000):
        twin.cycle()
        if twin.started:
            break
    # its verdict does not overwrite the answer still pending (read late, OK would answer the commit)
    assert twin.started and (twin.state.status, twin.state.ack_token, twin.state.active_version) == \
        (Status.PLC_STARTING, DEAD, 5)
    twin.write_symbol("commit", done_value(DEAD).to_bytes(4, "little"))   # the client withdraws, commits again
    twin.cycle()
    assert (twin.state.status, twin.state.ack_token) == (Status.OK, 0)                # the verdict shows now
    twin.write_symbol("commit", DEAD.to_bytes(4, "little"))
    for _ in range(5_000):
        twin.cycle()
        if twin.state.ack_token == DEAD:
            break
    assert (twin.state.status, twin.state.active_version) == (Status.OK, 6)


@pytest.mark.parametrize("mock, link", MOCKS)
def test_a_push_right_after_a_restart_waits_for_the_start_up_check(mock, link):
    with running(_plc(mock)) as plc:
        plc.twin.seed(make_table(version=1, n_phi=100, n_theta=100))
        plc.restart()
        rep = push(link(plc), make_table(version=2), OPTIONS)
        assert rep.result == "ok" and plc.twin.state.active_version == 2
