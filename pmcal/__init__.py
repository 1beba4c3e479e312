"""pmcal: calibration workbench for parallel mechanisms (application layer: CLI, files, reports).

The numerics live in :mod:`calib`, the MuJoCo digital twin in :mod:`twin`, the PLC transport in
:mod:`bridge`. This package only wires them to files and the command line.
"""

__version__ = "0.1.0"
