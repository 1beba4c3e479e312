"""A calibration of a machine described by a folder (the closed-chain core): the same calls as the
over-constrained PM's :class:`pmcal.ocpm.calibration.Calibration`, so that the library API reads the same for
every machine (``pmcal.identify`` -> ``cal.setpoints`` -> ``cal.compensation_table`` -> ``cal.save``).

The calibration owns its parameters document (docs/formats.md, "Any machine": every error's value in mm
or deg, the base set, the covariance, the prior, the fit's quality), which is what ``pmcal --machine DIR
identify`` writes; loading it needs the machine (its twin says each error's unit).

Example
-------
>>> import pmcal                                                            # doctest: +SKIP
>>> m = pmcal.Machine.builtin("delta_3dof")                                 # doctest: +SKIP
>>> cal = pmcal.identify(pmcal.read_measurements("m.csv", m))               # doctest: +SKIP
>>> cal.setpoints([[0.0, 0.0, -800.0]])                                     # doctest: +SKIP
array([[...]])
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pmcal.bridge.comptable import CompTable
from pmcal.calibration_document import CalibrationDocument
from pmcal.chain import (campaign_quality, compensate, compensation_table, identify as identify_errors,
                         params_document, table_refusal)
from pmcal.errors import InputError
from pmcal.io_chain import ChainMeasurements, read_params


#: the campaign that fixes a calibration flagged not usable (named by refusals)
CAMPAIGN_FIX = "measure poses spread over the workspace ('pmcal twin plan' plans them)"


@dataclass
class ChainCalibration(CalibrationDocument):
    """The identified machine of a folder: its errors and the document that records them.

    Attributes
    ----------
    machine : pmcal.Machine
        The machine (folder) the parameters belong to.
    document : dict
        The parameters document (docs/formats.md, "Any machine"), with its ``quality`` object.
    path : str
        The file it was loaded from ("" when identified here): what a refusal names.
    """

    machine: object
    document: dict
    path: str = ""

    def setpoints(self, targets, *, force: bool = False) -> np.ndarray:
        """Motor commands (n, M) (deg revolute, mm prismatic) that put the task point at ``targets`` (n, C),
        in the task's coordinates and units (machine.toml ``[task]``: mm and deg), by the identified
        machine's inverse kinematics. Refused (InputError) for a calibration flagged not usable unless
        ``force``; an unreachable target is an InputError naming its row."""
        self.refuse_unusable(force, self.machine.name, CAMPAIGN_FIX)
        task = np.atleast_2d(np.asarray(targets, float))
        width = len(self.machine.spec.task.coordinates)
        if task.shape[1] != width:
            raise InputError(f"targets need {width} columns ({', '.join(self.machine.spec.task.coordinates)}), "
                             f"got {task.shape[1]}", field="targets")
        return compensate(self.machine, self.params, task)

    def compensation_table(self, version: int = 1, grid=None, *, absolute: bool | None = None,
                           force: bool = False) -> CompTable:
        """The PLC's compensation table (format 4, docs/compensation_table.md) over machine.toml's ``[table]``
        axes: corrections to the controller's nominal IK by default, absolute commands with ``absolute``.
        ``grid``: nodes per axis (default ``[table] nodes``). InputError for a machine without a table, or a
        calibration flagged not usable (unless ``force``)."""
        why = table_refusal(self.machine)
        if why:
            raise InputError(why, field="compensation_table")
        self.refuse_unusable(force, self.machine.name, CAMPAIGN_FIX)
        return compensation_table(self.machine, self.params, int(version), grid, absolute=absolute)

    @classmethod
    def load(cls, path: str | Path, machine) -> ChainCalibration:
        """Read a parameters JSON of ``machine`` (checked: its mechanism, error keys and value sizes)."""
        units = dict(zip(machine.twin.error_keys, machine.twin.error_units()))
        _, doc = read_params(path, machine.spec, units)
        return cls(machine, doc, path=str(path))

    @classmethod
    def identify(cls, machine, meas: ChainMeasurements, sigma_mm: float | None = None) -> ChainCalibration:
        """Identify ``machine``'s errors from a campaign (:func:`pmcal.chain.identify`) and judge it
        (:func:`pmcal.chain.campaign_quality`)."""
        res = identify_errors(machine, meas, sigma_mm)
        quality = campaign_quality(machine, meas, res, sigma_mm)
        return cls(machine, dict(params_document(machine, res, meas.path or None), quality=quality))

