"""Persistence of the shipped ST (interpreted): FB_CompTableManager saves the persistent data with
FB_WritePersistentData after each swap and acknowledges only then, so a power cut without UPS after the
acknowledgement brings the new table back, a cut before it the old one, never a mix."""

from __future__ import annotations

from pmcal.bridge import plc_types
from pmcal.bridge.plc_runtime import PlcTwin
from pmcal.bridge.plc_types import Header, State, Status, done_value, shadow_rows
from tests.bridge_fixtures import make_table

TOKEN = 0xDAFE0001


def _stage_and_commit(twin: PlcTwin, table) -> None:
    """Claim the staging area, stage ``table`` and write the commit token (no cycle after it)."""
    twin.write_symbol("staging_claim", TOKEN.to_bytes(4, "little"))
    twin.cycle()
    rows = shadow_rows(table)
    twin.write_symbol("shadow_header", Header.of(table).pack())
    twin.write_symbol("shadow", rows + bytes(plc_types.SHADOW_SIZE - len(rows)))
    twin.write_symbol("commit", TOKEN.to_bytes(4, "little"))


def _commit_until(twin: PlcTwin, table, done) -> None:
    _stage_and_commit(twin, table)
    for _ in range(20_000):
        assert twin.cycle(), twin.fault
        if done(twin.state):
            return
    raise AssertionError(twin.state)


def _after_power_cut(twin: PlcTwin):
    twin.power_cut()
    for _ in range(20_000):
        if not twin.cycle() or twin.started:
            break
    assert twin.started and not twin.stopped
    return twin.active_table()


def test_an_acknowledged_table_survives_a_power_cut():
    old, new = make_table(version=1), make_table(version=2, offset_deg=0.3)
    twin = PlcTwin()
    twin.seed(old)
    _commit_until(twin, new, lambda s: s.ack_token == TOKEN)
    assert (twin.state.status, twin.state.active_version) == (Status.OK, 2)
    header, values = _after_power_cut(twin)
    assert header == Header.of(new) and values.tobytes() == new.values.tobytes()
    assert twin.state.active_crc == new.crc32()


def test_a_cut_after_the_swap_but_before_the_save_brings_the_old_table_back_whole():
    old, new = make_table(version=1), make_table(version=2, offset_deg=0.3)
    twin = PlcTwin()
    twin.seed(old)
    _commit_until(twin, new, lambda s: s.state == State.PERSISTING)
    assert (twin.state.active_version, twin.state.ack_token) == (2, 0)      # swapped, not yet acknowledged
    header, values = _after_power_cut(twin)
    assert header == Header.of(old) and values.tobytes() == old.values.tobytes()


def test_a_cut_while_the_commit_waits_for_motion_keeps_the_old_table():
    old, new = make_table(version=1), make_table(version=2, offset_deg=0.3)
    twin = PlcTwin()
    twin.seed(old)
    twin.motion_idle = False
    _commit_until(twin, new, lambda s: s.state == State.WAIT_MOTION)
    header, values = _after_power_cut(twin)
    assert header == Header.of(old) and values.tobytes() == old.values.tobytes()
    # the version order survives too: the old version is still refused
    twin.motion_idle = True
    _commit_until(twin, make_table(version=1, offset_deg=0.1), lambda s: s.ack_token == TOKEN)
    assert twin.state.status == Status.STALE_VERSION


def test_the_start_up_verdict_does_not_answer_a_commit_made_while_starting():
    """A commit written while the PLC re-checks its persistent table after a restart is answered
    PLC_STARTING; the start-up check finishing afterwards must not turn that pending answer into OK (a
    client reading the acknowledgement late would take OK for its own commit: 'rejected version 4: OK',
    the table not active). The client commits again (0, then its token) and gets the real verdict."""
    old, new = make_table(version=3), make_table(version=4, offset_deg=0.3)
    twin = PlcTwin()
    twin.seed(old)
    twin.restart()
    assert not twin.started
    _stage_and_commit(twin, new)
    twin.cycle()
    assert (twin.state.ack_token, twin.state.status) == (TOKEN, Status.PLC_STARTING)
    for _ in range(SETTLE):                               # the client is slow: the start-up check ends
        twin.cycle()
        if twin.started:
            break
    assert twin.started
    twin.cycle()
    st = twin.state
    assert st.ack_token == TOKEN and st.status == Status.PLC_STARTING, (st.status, st.active_version)
    twin.write_symbol("commit", done_value(TOKEN).to_bytes(4, "little"))
    twin.cycle()
    assert twin.state.ack_token == 0
    twin.write_symbol("commit", TOKEN.to_bytes(4, "little"))
    for _ in range(SETTLE):
        twin.cycle()
        if twin.state.ack_token == TOKEN:
            break
    assert (twin.state.status, twin.state.active_version) == (Status.OK, 4)


#: cycles enough for a start-up check or a commit of the small test table
SETTLE = 20_000
