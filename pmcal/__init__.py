"""pmcal: calibration workbench for parallel mechanisms with a MuJoCo digital twin and a PLC bridge.

The library API (:mod:`pmcal.api`), in the style of :mod:`scipy.optimize`::

    import pmcal
    meas = pmcal.read_measurements("m.csv")          # the measurement CSV (docs/formats.md)
    cal = pmcal.identify(meas)                       # whole closed chain; model="paper", method="hga"
    m = cal.setpoints(phi_deg, theta_deg)            # (n, 2) motor commands, degrees
    table = cal.compensation_table(version=7)        # CompTable; grid=(n_phi, n_theta)
    table.save("t.json")
    report = pmcal.push(table, ads="NETID@HOST:PORT")   # or modbus="HOST:PORT"
    machine = pmcal.Machine.from_folder("my_delta")  # any machine folder (docs/ADDING_A_MACHINE.md):
    meas = pmcal.read_measurements("d.csv", machine) # the same lines then (a ChainCalibration)

Sub-packages, in layer order (each imports only those before it; docs/DEVELOPING.md):
:mod:`pmcal.mechanism` (machine description), :mod:`pmcal.twin` (MuJoCo digital twin),
:mod:`pmcal.calib` (identification, diagnosis, compensation numerics), :mod:`pmcal.bridge` (PLC
transport), and the application (this package: API, command line, file formats, reports).
"""

__version__ = "0.2.0"

__all__ = ["Calibration", "ChainCalibration", "ChainMeasurements", "CompTable", "Machine", "Measurements",
           "PlanarCalibration", "PlanarMeasurements", "PushReport", "identify", "load_calibration", "open_link",
           "push", "read_measurements", "__version__"]


def __getattr__(name: str):
    # Lazy re-export of pmcal.api: `import pmcal` (and so every `pmcal ...` command, whose entry point
    # lives in this package) would otherwise import MuJoCo, SciPy, pyads and pymodbus up front: measured on
    # the 2-core reference machine, `pmcal --help` takes 0.4 s, `import pmcal.api` 2.9 s. Not a cycle:
    # pmcal.api imports the lower layers only.
    if name in __all__:
        from pmcal import api

        return getattr(api, name)
    raise AttributeError(f"module 'pmcal' has no attribute {name!r}")
