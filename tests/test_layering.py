"""The one-way import contract (tests/layering.py) holds, and the checker does catch a reverse import."""

from layering import LAYERS, check, layer_of, modules, wing_of, wing_violations


def test_every_module_has_a_layer():
    mods = modules()
    assert "pmcal.calib.ocpm.fullchain" in mods and "pmcal.twin.ocpm.forward" in mods
    assert all(layer_of(m) >= 0 for m in mods)


def test_imports_point_one_way():
    bad = check({m: p.read_text(encoding="utf-8") for m, p in modules().items()})
    assert not bad, "\n".join(map(str, bad))


def test_a_reverse_import_is_caught():
    """A twin module importing the identification layer, a calib module importing the twin (even inside a
    function), and the bridge importing numerics are each reported; a downward import is not."""
    sources = {
        "pmcal.twin.ocpm.machine": "from pmcal.calib.ocpm.fullchain import identify_full\n",
        "pmcal.calib.ocpm.fullchain": "def f():\n    from pmcal.twin.ocpm.machine import Twin\n",
        "pmcal.bridge.ads": "import pmcal.calib.solvers\n",
        "pmcal.mechanism.ocpm.config": "from ..rotations import tilt_torsion\nfrom pmcal.errors import InputError\n",
    }
    bad = check(sources)
    assert {(v.importer, v.imported) for v in bad} == {
        ("pmcal.twin.ocpm.machine", "pmcal.calib.ocpm.fullchain.identify_full"),
        ("pmcal.calib.ocpm.fullchain", "pmcal.twin.ocpm.machine.Twin"),
        ("pmcal.bridge.ads", "pmcal.calib.solvers"),
    }
    assert [LAYERS[layer_of(m)][0] for m in ("pmcal.errors", "pmcal.mechanism.rigid", "pmcal.cli")] == [
        "foundation", "machine description", "application: cli"]


def test_the_application_sub_layers_point_one_way_too():
    """An application module (a handler) importing the command parsers, the library importing an
    application, and a file format importing the library are each reported."""
    sources = {
        "pmcal.apps.chain": "from pmcal.commands.options import KIND_NAMES\n",
        "pmcal.machines": "def f():\n    import pmcal.apps.chain\n",
        "pmcal.io_chain": "from pmcal.chain import identify\n",
        "pmcal.commands.routing": "from pmcal.apps import chain\n",
    }
    assert {(v.importer, v.imported) for v in check(sources)} == {
        ("pmcal.apps.chain", "pmcal.commands.options.KIND_NAMES"), ("pmcal.machines", "pmcal.apps.chain"),
        ("pmcal.io_chain", "pmcal.chain.identify")}


def test_the_generic_core_imports_no_seeded_machine_and_the_machines_not_each_other():
    bad = wing_violations({m: p.read_text(encoding="utf-8") for m, p in modules().items()})
    assert not bad, "\n".join(map(str, bad))


def test_a_generic_module_importing_a_wing_is_caught():
    """A generic twin module importing ocpm_2dof's assembler (inside a function too), a planar module importing
    ocpm's, and the bridge importing ocpm's geometry are each reported; the front door routing is not."""
    sources = {
        "pmcal.twin.closed_chain": "def f():\n    from pmcal.twin.ocpm.assembly import BatchAssembler\n",
        "pmcal.twin.planar.twin": "from pmcal.twin.ocpm.machine import Twin\n",
        "pmcal.bridge.nominal": "from pmcal.mechanism.ocpm.config import default_geometry\n",
        "pmcal.api": "from pmcal.ocpm.calibration import Calibration\n",
        "pmcal.ocpm.calibration": "from pmcal.history import make_record\n",
    }
    assert {(v.importer, v.imported) for v in wing_violations(sources)} == {
        ("pmcal.twin.closed_chain", "pmcal.twin.ocpm.assembly.BatchAssembler"),
        ("pmcal.twin.planar.twin", "pmcal.twin.ocpm.machine.Twin"),
        ("pmcal.bridge.nominal", "pmcal.mechanism.ocpm.config.default_geometry")}
    assert (wing_of("pmcal.calib.ocpm.fullchain"), wing_of("pmcal.twin.closed_chain")) == ("ocpm_2dof", None)


def test_every_command_of_a_machine_resolves_to_its_handler_not_a_module():
    """A wing's application package routes a command to the function of that name; a submodule named like a
    command would shadow it once imported (the package attribute becomes the module)."""
    import importlib
    import types

    from pmcal.commands.routing import application
    from pmcal.machines import Machine

    commands = ("twin_measure", "twin_render", "twin_plan", "identify", "compensate", "evaluate", "demo",
                "targets", "diagnose", "export_model", "import_campaign", "loop")
    for name in ("ocpm_2dof", "planar_2dof", "delta_3dof"):
        app = application(Machine.builtin(name))
        for sub in getattr(app, "__path__", None) and __import__("pkgutil").iter_modules(app.__path__) or ():
            importlib.import_module(f"{app.__name__}.{sub.name}")      # every submodule loaded, as in a session
        for command in commands:
            handler = getattr(app, command, None)
            assert handler is None or isinstance(handler, types.FunctionType), (name, command, handler)


def test_the_table_contract_and_the_library_do_not_need_the_simulated_plc():
    """pmcal.bridge without its simulator (the table, the clients, the transfer), the file formats and the
    library import nothing of pmcal.bridge.simulator (the ``sim`` extra): a plain install pushes to real PLCs."""
    from layering import imports_of

    bad = []
    for mod, path in modules().items():
        contract = mod.startswith("pmcal.bridge") and not mod.startswith("pmcal.bridge.simulator")
        if contract or layer_of(mod) in (layer_of("pmcal.api"), layer_of("pmcal.io_chain")):
            bad += [(mod, imp) for imp, _ in imports_of(mod, path.read_text(encoding="utf-8"))
                    if imp.startswith("pmcal.bridge.simulator")]
    assert not bad, bad
