"""TwinCAT 3 sources of the PLC side of the compensation table (``DUTs/``, ``GVLs/``, ``POUs/``).

Data, shipped as package data of ``pmcal.plc`` so that an installed pmcal can hand them to a TwinCAT
engineer (:data:`ROOT`); see ``README.md`` in this folder for the import procedure. :func:`constant` reads
one of the project's parameters (``GVL_CompTableParam``) as the ST declares it.
"""

import re
from pathlib import Path

#: Folder holding the TwinCAT sources.
ROOT = Path(__file__).resolve().parent


def constant(name: str) -> str:
    """The initial value of constant ``name`` of ``GVLs/GVL_CompTableParam`` as written in the ST (e.g.
    ``constant("REF_A_MM")`` -> ``"150.0"``); KeyError when the GVL declares no such constant."""
    text = (ROOT / "GVLs" / "GVL_CompTableParam.TcGVL").read_text(encoding="utf-8")
    found = re.search(rf"^\s*{re.escape(name)}\s*:\s*\w+\s*:=\s*([^;]+);", text, re.M)
    if found is None:
        raise KeyError(f"GVL_CompTableParam has no constant {name}")
    return found[1].strip()
