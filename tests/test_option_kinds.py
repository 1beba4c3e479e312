"""Options only some machines have say so where they are added (``kinds=``, pmcal.commands.options): every
other machine refuses them in one line naming the machine (exit 2), writes nothing, and leaves them out of
``--help``. Before, planar_2dof accepted ocpm_2dof's options hidden and ignored them: ``twin measure
--effect backlash=0.1`` measured a campaign without the backlash and exited 0."""

from __future__ import annotations

import argparse

import pytest

from pmcal.cli import build_parser, main
from pmcal.commands.options import KINDS, NotForThisMachine

MACHINES = ("ocpm_2dof", "planar_2dof", "delta_3dof")


def _refused(machine: str) -> list[tuple[str, argparse.Action]]:
    """(full command name, action) of every option ``machine`` does not have."""
    parser = build_parser(machine)
    return [(name, a) for name, cmd in parser.pmcal_commands.items() for a in cmd.parser._actions
            if isinstance(a, NotForThisMachine)]


def _argv(machine: str, command: str, action: argparse.Action) -> list[str]:
    values = [] if action.nargs == 0 else ["1"]
    return ["--machine", machine, *command.split(), action.option_strings[-1], *values]


@pytest.mark.parametrize("machine", MACHINES)
def test_an_option_of_other_machines_is_refused_in_one_line_naming_the_machine(machine, capsys, tmp_path,
                                                                               monkeypatch):
    monkeypatch.chdir(tmp_path)
    refused = _refused(machine)
    assert len(refused) >= 4, "every machine lacks some of the others' options"
    for command, action in refused:
        assert set(action.kinds) <= set(KINDS) and action.machine == machine
        with pytest.raises(SystemExit) as stop:
            main(_argv(machine, command, action))
        err = capsys.readouterr().err.strip()
        assert stop.value.code == 2, (command, action.option_strings)
        assert len(err.splitlines()) == 1
        assert f"{action.option_strings[-1]} is not an option of machine {machine}: only" in err
        assert action.option_strings[-1] not in build_parser(machine).pmcal_commands[command].parser.format_help()
    assert not list(tmp_path.iterdir()), "nothing written"


def test_planar_no_longer_ignores_an_effect_it_cannot_simulate(tmp_path, capsys):
    out = tmp_path / "m.csv"
    with pytest.raises(SystemExit) as stop:
        main(["--machine", "planar_2dof", "twin", "measure", "-o", str(out), "--effect", "backlash=0.1"])
    assert stop.value.code == 2 and not out.exists()
    assert "--effect is not an option of machine planar_2dof: only ocpm_2dof has it" in capsys.readouterr().err


def test_the_seeded_machines_and_a_folder_each_keep_their_own_options():
    """What each kind has, spot-checked against the commands that use them (a kind left out by mistake
    would refuse an option its application reads)."""
    has = {m: {(c, a.option_strings[-1]) for c, a in _refused(m)} for m in MACHINES}
    assert ("twin measure", "--effect") not in has["ocpm_2dof"]
    assert ("twin measure", "--effect") in has["planar_2dof"] and ("twin measure", "--effect") in has["delta_3dof"]
    assert ("twin measure", "--servo-noise") not in has["planar_2dof"]
    assert ("compensate", "--absolute") not in has["delta_3dof"]
    assert ("compensate", "--table") in has["planar_2dof"] and ("compensate", "--table") not in has["delta_3dof"]
    assert ("identify", "--history") not in has["delta_3dof"] and ("identify", "--history") in has["planar_2dof"]
    assert ("twin measure", "--plan") not in has["delta_3dof"] and ("twin measure", "--plan") in has["ocpm_2dof"]


def test_a_kind_that_does_not_exist_is_a_programming_error():
    from pmcal.commands.options import CommandSet

    parser = argparse.ArgumentParser()
    commands = CommandSet(parser.add_subparsers(), {}, {}, kind="chain", machine="m")
    p = commands.add_parser("identify")
    with pytest.raises(ValueError, match="unknown machine kind"):
        p.add_argument("--robust", action="store_true", help="robust", kinds=("ocpm2dof",))
