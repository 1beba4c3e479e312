"""The ST in plc/ uses only what TwinCAT 3.1 provides: every operator, statement, type, function,
function block, library symbol and attribute pragma it uses and does not define itself is in
plc/allowlist.toml, each entry naming the Beckhoff Infosys document that defines it. Nothing else passes.

The sources are parsed with blark (an independent IEC 61131-3 / TwinCAT grammar); the names the project
declares (POUs, DUTs, GVLs, variables, members, enum values, methods) are collected from the parse trees,
everything else a tree holds must be on the list.
"""

from __future__ import annotations

import re
import tomllib
import xml.etree.ElementTree as ET

import pytest

lark = pytest.importorskip("lark")
from tests.test_bridge_plc_blark import FILES, PLC, _parsed  # noqa: E402  (one parse per file and session)

ALLOW = tomllib.loads((PLC / "allowlist.toml").read_text(encoding="utf-8"))
SECTIONS = ("operator", "statement", "keyword", "type", "function", "function_block", "member", "attribute")

#: rules whose direct IDENTIFIER child is a name the project declares
_DECLARING = {"global_var_list", "enumerated_value", "union_element_declaration", "structure_type_declaration",
              "enumerated_type_declaration", "union_type_declaration", "function_declaration",
              "function_block_type_declaration", "program_declaration", "function_block_method_declaration"}
#: rules whose tokens are literals (numbers, strings, booleans): always allowed
_LITERALS = {"integer", "real_literal", "hex_integer", "binary_integer", "octal_integer", "string_literal",
             "bit_string_literal", "duration", "true", "false", "constant"}
_NAME_TOKENS = {"IDENTIFIER", "DOTTED_IDENTIFIER"}
_OPERATOR_TOKENS = {"ASSIGNMENT", "COMPARE_OP", "EQUALS_OP", "ADD_OPERATOR", "MULTIPLY_OPERATOR", "UNARY_OPERATOR",
                    "LOGICAL_AND", "LOGICAL_OR", "LOGICAL_XOR", "LOGICAL_AND_THEN", "LOGICAL_OR_ELSE",
                    "REF_ASSIGNMENT", "DEREFERENCED", "OUTPUT_ASSIGNMENT"}
_TYPE_TOKENS = {"NUMERIC_TYPE_NAME", "BIT_STRING_TYPE_NAME", "STRING", "DATE_TYPE_NAME", "REFERENCE_TO",
                "POINTER_TO", "TIME_TYPE_NAME"}


def _walk(tree, parent=None):
    """(token, rule of its parent node, rule of the grandparent) for every token of a tree."""
    stack = [(tree, None)]
    while stack:
        node, up = stack.pop()
        for child in node.children:
            if isinstance(child, lark.Tree):
                stack.append((child, node.data))
            elif isinstance(child, lark.Token):
                yield child, str(node.data), str(up)


def _uses():
    """(declared names, used names, operators, statements, types, keywords, attributes), over all files."""
    declared, names, ops, statements, types, keywords, attributes = set(), {}, {}, {}, {}, {}, {}
    for path in FILES:
        root = ET.parse(path).getroot()
        for obj in root:
            declared.add(obj.get("Name"))
            for m in obj.iter("Method"):
                declared.add(m.get("Name"))
        attributes.update({a: path.name for a in re.findall(r"\{attribute '(\w+)'", path.read_text())})
        for result in _parsed(path):
            tree = result.tree
            for sub in tree.iter_subtrees():
                if str(sub.data).endswith("_statement"):
                    statements.setdefault(str(sub.data), path.name)
            for tok, rule, up in _walk(tree):
                text = str(tok)
                if rule in _LITERALS or tok.type in ("INTEGER",):
                    continue
                if tok.type in _NAME_TOKENS:
                    if rule in _DECLARING or (rule == "variable_name" and up in ("var1", "structure_element_declaration")):
                        declared.add(text)
                    else:
                        names.setdefault(text, path.name)
                elif tok.type in _OPERATOR_TOKENS:
                    ops.setdefault(text.upper(), path.name)
                elif tok.type in _TYPE_TOKENS:
                    types.setdefault(text.upper(), path.name)
                else:
                    keywords.setdefault(text.upper(), path.name)
    return declared, names, ops, statements, types, keywords, attributes


USES = _uses()


def test_every_entry_names_its_beckhoff_document():
    assert set(ALLOW) <= set(SECTIONS)
    for section, entries in ALLOW.items():
        for name, doc in entries.items():
            assert isinstance(doc, str) and ("Infosys" in doc), (section, name, doc)


@pytest.mark.parametrize("kind, index, sections", [
    ("operator", 2, ("operator",)), ("statement", 3, ("statement",)), ("type", 4, ("type",)),
    ("keyword", 5, ("keyword",)), ("attribute", 6, ("attribute",)),
])
def test_operators_statements_types_and_pragmas_are_on_the_list(kind, index, sections):
    allowed = {n.upper() for s in sections for n in ALLOW.get(s, {})}
    missing = {n: f for n, f in USES[index].items() if n.upper() not in allowed}
    assert not missing, f"{kind}s used in plc/ but not on plc/allowlist.toml: {missing}"


def test_every_name_plc_does_not_define_is_a_documented_twincat_symbol():
    declared, names = USES[0], USES[1]
    allowed = {n for s in ("function", "function_block", "type", "member", "keyword") for n in ALLOW.get(s, {})}
    missing = {n: f for n, f in names.items() if n not in declared and n not in allowed}
    assert not missing, f"names used in plc/ that neither plc/ nor plc/allowlist.toml defines: {missing}"


def test_the_list_holds_nothing_unused():
    """A stale entry would let a later edit use a symbol nobody checked."""
    declared, names, ops, statements, types, keywords, attributes = USES
    used = {n.upper() for n in (*names, *ops, *statements, *types, *keywords, *attributes)}
    unused = {(s, n) for s, entries in ALLOW.items() for n in entries if n.upper() not in used}
    assert not unused, unused


def test_no_atan2_no_nan_producer():
    """TwinCAT 3 has no ATAN2 operator (F_CompTableAtan2 replaces it); no constant NaN/infinity expression."""
    names = USES[1]
    assert "ATAN2" not in {n.upper() for n in names}
    for path in FILES:
        code = re.sub(r"//[^\n]*|\(\*.*?\*\)", "", path.read_text(), flags=re.S)
        assert not re.search(r"/\s*0(\.0*)?\b(?!\.?\d)", code), f"{path.name}: division by a literal zero"


# ---- the PLC project file -----------------------------------------------------------------------

_MSBUILD = "{http://schemas.microsoft.com/developer/msbuild/2003}"


def test_project_file_lists_every_object_on_disk_and_nothing_else():
    """plc/CompTable.plcproj (MSBuild XML as XAE writes it) compiles exactly the files of plc/ and
    references the four libraries the allow-list names."""
    root = ET.parse(PLC / "CompTable.plcproj").getroot()
    compiled = {c.get("Include").replace("\\", "/") for c in root.iter(f"{_MSBUILD}Compile")}
    assert compiled == {str(p.relative_to(PLC)) for p in FILES} | {"PlcTask.TcTTO", "PersistTask.TcTTO"}
    assert all(c.findtext(f"{_MSBUILD}SubType") == "Code" for c in root.iter(f"{_MSBUILD}Compile"))
    libraries = {r.get("Include") for r in root.iter(f"{_MSBUILD}PlaceholderReference")}
    assert libraries == {"Tc2_Standard", "Tc2_System", "Tc2_Utilities", "Tc2_MC2"}
    documented = " ".join(doc for entries in ALLOW.values() for doc in entries.values())
    assert all(f"Library {lib} " in documented for lib in libraries)      # each one is used and documented


def test_the_project_opens_with_a_task_that_calls_prg_comptable():
    """plc/PlcTask.TcTTO (a task object as XAE writes it: cycle time in microseconds, priority, the POU
    calls in order) runs PRG_CompTable first, then the sample motion code, every 1 ms; each call names a
    PROGRAM of plc/, and the interpreter's task (PlcRuntime) calls PRG_CompTable the same way."""
    from pmcal.bridge.simulator.plc_runtime import PlcRuntime

    task = ET.parse(PLC / "PlcTask.TcTTO").getroot().find("Task")
    calls = [c.findtext("Name") for c in task.findall("PouCall")]
    assert task.get("Name") == "PlcTask" and re.fullmatch(r"\{[0-9a-f-]{36}\}", task.get("Id"))
    assert (int(task.findtext("CycleTime")), calls) == (1000, ["PRG_CompTable", "PRG_CompTableMotionSample"])
    assert 0 < int(task.findtext("Priority")) <= 31
    programs = {p.stem for p in FILES if p.suffix == ".TcPOU" and "PROGRAM " + p.stem in p.read_text()}
    assert set(calls) <= programs
    rt = PlcRuntime(task=calls)
    assert rt.cycle_s == int(task.findtext("CycleTime")) * 1e-6 and rt.run(3) == 3
    # the save runs in its own task, slower and of lower priority (a higher number), as the interpreter
    # runs it (every SAVE_EVERY task cycles, after the task)
    from pmcal.bridge.simulator.plc_runtime.runtime import SAVE_EVERY, SAVE_PROGRAM

    save = ET.parse(PLC / "PersistTask.TcTTO").getroot().find("Task")
    assert [c.findtext("Name") for c in save.findall("PouCall")] == [SAVE_PROGRAM]
    assert int(save.findtext("Priority")) > int(task.findtext("Priority"))
    assert int(save.findtext("CycleTime")) == SAVE_EVERY * int(task.findtext("CycleTime"))
    assert SAVE_PROGRAM not in calls


def test_axes_reach_the_function_blocks_in_out_and_no_pou_declares_one():
    for path in FILES:
        if path.suffix != ".TcPOU":
            continue
        decl = "\n".join(d.text or "" for d in ET.parse(path).getroot().iter("Declaration"))
        for block in re.findall(r"\b(VAR(?:_INPUT|_OUTPUT|_TEMP|_STAT)?)\b(.*?)\bEND_VAR\b", decl, re.S):
            assert "AXIS_REF" not in re.sub(r"//[^\n]*", "", block[1]), f"{path.name}: AXIS_REF in {block[0]}"
    idle = ET.parse(PLC / "POUs" / "FB_CompTableMotionIdle.TcPOU").getroot().find(".//Declaration").text
    assert re.search(r"VAR_IN_OUT\s+Axis1\s*:\s*AXIS_REF;", idle)
