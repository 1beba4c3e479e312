"""Each command declares its files once, where it adds the option (``role=``, ``suffixes=``, ``companion=``,
pmcal.commands.options.FileRole); the command line's output guard reads them from there."""

from __future__ import annotations

import re

import pytest

from pmcal.cli import build_parser, input_paths, output_paths

#: a metavar that names a file or a folder
FILE_METAVAR = re.compile(r"(\.(json|csv|png|xml|html|txt)$)|^(DIR|FILE|TABLE)$")
#: file options deliberately without a role, and why
NO_ROLE = {("history", "folder"): "the history folder is read as a whole; its report may be written inside it",
           ("identify", "history"): "a folder records are added to, never replaced (pmcal.history.check_history_dir)",
           ("identify", "frame"): "a frame name, or tracker:FILE whose file is checked where it is read",
           ("diagnose", "frame"): "a frame name, or tracker:FILE whose file is checked where it is read"}


@pytest.mark.parametrize("machine", ["ocpm_2dof", "planar_2dof", "delta_3dof"])
def test_every_file_option_declares_its_role(machine):
    parser = build_parser(machine)
    for name, cmd in parser.pmcal_commands.items():
        for action in cmd.parser._actions:
            if action.metavar and FILE_METAVAR.search(str(action.metavar)) and (name, action.dest) not in NO_ROLE:
                assert action.dest in cmd.files, f"pmcal {name} {action.option_strings or action.dest}: no role"


def test_the_guard_reads_the_declared_roles():
    parser = build_parser("ocpm_2dof")
    args = parser.parse_args(["compensate", "p.json", "--table", "t.json"])
    assert output_paths(args, suffixes=False) == [("--table", "t.json", False), ("--table", "t.csv", False)]
    assert input_paths(args) == [("PARAMS.json", "p.json")]
    args = parser.parse_args(["diagnose", "m.csv", "--json", "d.json", "--report", "rep"])
    assert output_paths(args) == [("--json", "d.json", False), ("--report", "rep", True)]
    files = parser.pmcal_commands["export-model"].files
    assert files["output"].suffixes == (".xml",) and files["output"].companion == (".toml", "pmcal.export_model")
