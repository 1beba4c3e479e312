"""What every calibration that owns its parameters document offers (a machine folder's
:class:`~pmcal.chain_calibration.ChainCalibration`, planar_2dof's
:class:`~pmcal.planar.calibration.PlanarCalibration`): the identified values, the quality verdict and its
refusal, the document and its file."""

from __future__ import annotations

from pathlib import Path

from pmcal.campaign_quality import refuse_unusable
from pmcal.fileio import check_output, write_json


class CalibrationDocument:
    """A calibration whose state is its parameters document. Subclasses (dataclasses) hold ``document`` (the
    parameters JSON: ``params`` in mm and deg, ``quality``, ...) and ``path`` (the file it was loaded from, ""
    when identified here: what a refusal names)."""

    document: dict
    path: str

    @property
    def params(self) -> dict[str, float]:
        """The identified errors ``{key: value}`` in their units (mm or deg)."""
        return {k: float(v) for k, v in self.document["params"].items()}

    @property
    def quality(self) -> dict:
        """The campaign's and the fit's quality (``usable``, ``why``, ...); empty when not judged."""
        q = self.document.get("quality")
        return dict(q) if isinstance(q, dict) else {}

    @property
    def usable(self) -> bool:
        return self.quality.get("usable", True) is not False

    def refuse_unusable(self, force: bool, name: str, fix: str) -> None:
        """InputError naming the file (else ``name``) when the calibration is flagged not usable, unless
        ``force`` (:func:`pmcal.campaign_quality.refuse_unusable`); ``fix``: the campaign that would do."""
        refuse_unusable(self.document, self.path or name, force, fix)

    def to_document(self) -> dict:
        """The parameters document (a copy)."""
        return dict(self.document)

    def save(self, path: str | Path) -> Path:
        """Write the parameters JSON (what the machine's ``pmcal identify`` writes), atomically, after the
        output guard (:func:`pmcal.fileio.check_output`); returns the path."""
        check_output(path, suffixes=(".json",))
        write_json(path, self.document)
        return Path(path)
