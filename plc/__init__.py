"""TwinCAT 3 sources of the PLC side of the compensation table (``DUTs/``, ``GVLs/``, ``POUs/``).

Data only, shipped as package data of ``pmcal.plc`` so that an installed pmcal can hand them to a
TwinCAT engineer (:data:`ROOT`); see ``README.md`` in this folder for the import procedure.
"""

from pathlib import Path

#: Folder holding the TwinCAT sources.
ROOT = Path(__file__).resolve().parent
