"""The one-way import contract (tests/layering.py) holds, and the checker does catch a reverse import."""

from layering import LAYERS, check, layer_of, modules


def test_every_module_has_a_layer():
    mods = modules()
    assert "pmcal.calib.ocpm.fullchain" in mods and "pmcal.twin.forward" in mods
    assert all(layer_of(m) >= 0 for m in mods)


def test_imports_point_one_way():
    bad = check({m: p.read_text(encoding="utf-8") for m, p in modules().items()})
    assert not bad, "\n".join(map(str, bad))


def test_a_reverse_import_is_caught():
    """A twin module importing the identification layer, a calib module importing the twin (even inside a
    function), and the bridge importing numerics are each reported; a downward import is not."""
    sources = {
        "pmcal.twin.machine": "from pmcal.calib.ocpm.fullchain import identify_full\n",
        "pmcal.calib.ocpm.fullchain": "def f():\n    from pmcal.twin.machine import Twin\n",
        "pmcal.bridge.ads": "import pmcal.calib.solvers\n",
        "pmcal.mechanism.ocpm.config": "from ..rotations import tilt_torsion\nfrom pmcal.errors import InputError\n",
    }
    bad = check(sources)
    assert {(v.importer, v.imported) for v in bad} == {
        ("pmcal.twin.machine", "pmcal.calib.ocpm.fullchain.identify_full"),
        ("pmcal.calib.ocpm.fullchain", "pmcal.twin.machine.Twin"),
        ("pmcal.bridge.ads", "pmcal.calib.solvers"),
    }
    assert [LAYERS[layer_of(m)][0] for m in ("pmcal.errors", "pmcal.mechanism.rigid", "pmcal.cli")] == [
        "foundation", "machine description", "application: cli"]


def test_the_application_sub_layers_point_one_way_too():
    """An application module (a handler) importing the command parsers, the library importing an
    application, and a file format importing the library are each reported."""
    sources = {
        "pmcal.apps.chain": "from pmcal.commands.options import ABSENT\n",
        "pmcal.machines": "def f():\n    import pmcal.apps.chain\n",
        "pmcal.io_chain": "from pmcal.chain import identify\n",
        "pmcal.commands.routing": "from pmcal.apps import chain\n",
    }
    assert {(v.importer, v.imported) for v in check(sources)} == {
        ("pmcal.apps.chain", "pmcal.commands.options.ABSENT"), ("pmcal.machines", "pmcal.apps.chain"),
        ("pmcal.io_chain", "pmcal.chain.identify")}
