"""Persistence of the shipped ST (interpreted): FB_CompTableManager saves the persistent data with
FB_WritePersistentData after each swap and acknowledges only then, so a power cut without UPS after the
acknowledgement brings the new table back, a cut before it the old one, never a mix. The table store is
PERSISTENT without 'hide' (TwinCAT persists no hidden variable): restart, Reset cold, download and power
cut keep the acknowledged table and its version order on both transports; with 'hide' put back the same
acceptance fails."""

from __future__ import annotations

import pytest

from pmcal.bridge import plc_types
from pmcal.bridge.simulator.plc_runtime import PlcTwin
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


# ---- what TwinCAT keeps: the shipped ST on both transports, and the same test with 'hide' put back ----

EVENTS = ["restart", "reset_cold", "download", "power_cut"]
MOCKS = [pytest.param("ads", id="ads"), pytest.param("modbus", id="modbus")]
#: a client's token for the rollback attempt (bit 31 set: a claim)
ROLLBACK = 0x80C0FFEE


def _mock(transport: str):
    from pmcal.bridge.simulator.ads_mock import AdsMockPlc
    from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc
    from tests.bridge_fixtures import ads_link, modbus_link

    mock = (AdsMockPlc if transport == "ads" else ModbusMockPlc)(lifetime_s=120.0, restart_s=0.3, boot_s=0.1)
    return mock, (ads_link if transport == "ads" else modbus_link)


@pytest.mark.parametrize("event", EVENTS)
@pytest.mark.parametrize("transport", MOCKS)
def test_the_acknowledged_table_survives_and_a_rollback_is_refused(transport, event):
    """Version 5 pushed over 3 and acknowledged; after a restart, a Reset cold, a download of the same
    program or a power cut without UPS the PLC serves version 5 again, and a client without the bridge's
    checks committing version 4 is refused STALE_VERSION by the PLC (nVersionFloor survived too)."""
    from pmcal.bridge.transfer import push
    from tests.bridge_fixtures import raw_commit, running

    mock, link = _mock(transport)
    with running(mock) as plc:
        plc.twin.seed(make_table(version=3))
        new = make_table(version=5, offset_deg=0.2)
        assert push(link(plc), new).result == "ok"
        getattr(plc, event)(0.3)
        assert plc.twin.wait_started()
        st = plc.twin.state
        assert (st.active_version, st.active_crc, st.status) == (5, new.crc32(), Status.OK)
        assert plc.twin.active_table()[1].tobytes() == new.values.tobytes()
        old = make_table(version=4, offset_deg=0.1)
        with link(plc) as ln:
            st = raw_commit(plc, ln, Header.of(old).pack(), shadow_rows(old), ROLLBACK)
        assert (st.status, st.active_version, st.active_crc) == (Status.STALE_VERSION, 5, new.crc32())


def _twin_survives(twin: PlcTwin, event: str) -> None:
    """The same acceptance at the PLC itself (no transport): version 5 acknowledged, the event, version 5
    served again, version 4 refused."""
    twin.seed(make_table(version=3))
    new = make_table(version=5, offset_deg=0.2)
    _commit_until(twin, new, lambda s: s.ack_token == TOKEN)
    assert (twin.state.status, twin.state.active_version) == (Status.OK, 5)
    twin.write_symbol("commit", done_value(TOKEN).to_bytes(4, "little"))
    twin.write_symbol("staging_claim", done_value(TOKEN).to_bytes(4, "little"))
    twin.cycle()
    getattr(twin, event)()
    for _ in range(SETTLE):
        if not twin.cycle() or twin.started:
            break
    assert twin.started and twin.state.active_version == 5, twin.state
    _commit_until(twin, make_table(version=4, offset_deg=0.1), lambda s: s.ack_token == TOKEN)
    assert (twin.state.status, twin.state.active_version) == (Status.STALE_VERSION, 5), twin.state


def _hidden_copy(tmp_path):
    """The shipped plc/ with {attribute 'hide'} put back on the persistent table (as before issue 30)."""
    import shutil
    from pathlib import Path

    import pmcal.plc

    folder = tmp_path / "plc"
    shutil.copytree(Path(pmcal.plc.__file__).parent, folder)
    gvl = folder / "GVLs" / "GVL_CompTableStore.TcGVL"
    text = gvl.read_text(encoding="utf-8")
    for name in ("aBuffer ", "aHeader ", "nActive ", "nVersionFloor "):
        text = text.replace(f"\t{name}", f"\t{{attribute 'hide'}}\n\t{name}", 1)
    assert text.count("{attribute 'hide'}\n\t") == 4
    gvl.write_text(text, encoding="utf-8")
    return folder


def _twin_of(folder=None) -> PlcTwin:
    from pmcal.bridge.simulator.plc_runtime import PlcRuntime, compile_project
    from pmcal.bridge.simulator.plc_runtime.comptable_plc import machine_constants

    program = compile_project(folder)
    return PlcTwin(runtime=PlcRuntime(program, constants=machine_constants("ocpm_2dof", 2, False)))


@pytest.mark.parametrize("event", EVENTS)
def test_with_hide_on_the_persistent_table_the_same_test_fails(tmp_path, event):
    """TwinCAT does not persist a variable under 'hide' (Infosys tc3_plc_intro, Attribute 'hide'): with
    the attribute put back, the table is gone after the event (version 0) and the acceptance fails; the
    shipped ST passes the same function."""
    _twin_survives(_twin_of(), event)
    hidden = _twin_of(_hidden_copy(tmp_path))
    with pytest.raises(AssertionError):
        _twin_survives(hidden, event)
    assert hidden.state.active_version == 0                 # the table in use did not survive


def test_hidden_variables_are_no_ads_symbols_and_retain_differs_from_persistent(tmp_path):
    """The remanence table of PlcRuntime (Infosys tc3_plc_intro, Remanent variables): RETAIN survives a
    restart and a power cut (NovRam) but not a Reset cold or a download; PERSISTENT survives all four; a
    hidden PERSISTENT variable survives none (and has no symbol); only Reset origin clears PERSISTENT."""
    from pmcal.bridge.simulator.plc_runtime import PlcRuntime, compile_files

    st = tmp_path / "remanent.st"
    st.write_text("""VAR_GLOBAL
    nVar : UDINT;
END_VAR
VAR_GLOBAL RETAIN
    nRetain : UDINT;
END_VAR
VAR_GLOBAL PERSISTENT
    nPersistent : UDINT;
    {attribute 'hide'}
    nHidden : UDINT;
END_VAR
PROGRAM MAIN
GVL.nVar := GVL.nVar + 1;
GVL.nRetain := GVL.nRetain + 1;
GVL.nPersistent := GVL.nPersistent + 1;
GVL.nHidden := GVL.nHidden + 1;
END_PROGRAM
""", encoding="utf-8")
    program = compile_files([st], cache=False)
    gv = program.gvls["gvl"]
    assert (gv["nhidden"].hidden, gv["nhidden"].persistent, gv["npersistent"].hidden) == (True, False, False)
    names = ("nVar", "nRetain", "nPersistent", "nHidden")
    kept = {"restart": (0, 3, 3, 0), "power_cut": (0, 3, 2, 0), "reset_cold": (0, 0, 3, 0),
            "download": (0, 0, 3, 0), "reset_origin": (0, 0, 0, 0)}
    for event, want in kept.items():
        rt = PlcRuntime(program, task=("MAIN",))
        rt.run(2)
        rt.mark_persistent_saved()                        # what FB_WritePersistentData saved: 2
        rt.run(1)
        if event == "download":
            rt.download(program)
        else:
            getattr(rt, event)()
        got = tuple(rt.read_value(f"GVL.{n}") for n in names)
        assert got == want, (event, got)


@pytest.mark.parametrize("port, survives", [(0, True), (851, False)])
def test_the_save_goes_to_the_runtimes_own_port(port, survives):
    """A second PLC runtime (AMS port 852): PRG_CompTableSave.nPlcPort = 0 (the default) saves this
    runtime's persistent data (TwinCAT_SystemInfoVarList._AppInfo.AdsPort); the former hard-coded 851
    saves the first runtime's data instead, answers OK, and a power cut brings the old table back."""
    from pmcal.bridge.simulator.plc_runtime import PlcRuntime
    from pmcal.bridge.simulator.plc_runtime.comptable_plc import machine_constants

    rt = PlcRuntime(constants=machine_constants("ocpm_2dof", 2, False), ams_port=852, other_ports=(851,))
    twin = PlcTwin(runtime=rt)
    rt.write_value("PRG_CompTableSave.nPlcPort", port)
    twin.seed(make_table(version=1))
    rt.write_value("PRG_CompTableSave.nPlcPort", port)                # seed restarted the runtime
    new = make_table(version=2, offset_deg=0.3)
    _commit_until(twin, new, lambda s: s.ack_token == TOKEN)
    assert (twin.state.status, twin.state.active_version) == (Status.OK, 2)
    header, _ = _after_power_cut(twin)
    assert (header == Header.of(new)) == survives
