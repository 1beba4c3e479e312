"""MJCF models and configuration of the machines, one folder each (MuJoCo Menagerie layout).

Data only: ``<machine>/<machine>.xml`` (the model), ``scene.xml`` (model + floor and light),
``machine.toml`` (nominal geometry, inertia, tracker targets and defaults), ``README.md`` with a picture.
Installed as package data of ``pmcal.mjcf``; :func:`machine_dir` finds a folder in an editable checkout and
in an installed wheel alike.
"""

from pathlib import Path

#: Folder holding one sub-folder per machine.
ROOT = Path(__file__).resolve().parent


def machine_dir(name: str) -> Path:
    """Folder of machine ``name`` (``ocpm_2dof`` or ``planar_2dof``)."""
    return ROOT / name
