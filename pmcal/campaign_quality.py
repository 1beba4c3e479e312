"""How much a measurement campaign determines, and whether its calibration may be used.

``pmcal identify`` records a ``quality`` object in the parameters file (docs/formats.md, "Campaign
quality"); ``pmcal compensate`` and ``pmcal push`` refuse a result flagged ``"usable": false`` unless
``--force`` (:func:`refuse_unusable`).

Two numbers say how much a campaign determines:

- **determined directions**: the effective number of fitted parameters, trace(C AᵀA) of the MAP fit
  (each direction counts 1 when the data fix it, 0 when only the prior holds it), rounded, of the number
  of parameters;
- **predicted pointing uncertainty**: the posterior covariance C propagated to the platform normal over
  :data:`pmcal.ocpm.calibration.QUALITY_GRID` (1 sigma, deg; ocpm_2dof's, :func:`pmcal.ocpm.calibration.full_chain_quality`): RMS and max over the grid. The same propagation of the prior
  (the manufacturing tolerances the machine's configuration assumes, ``docs/fullchain.md``) gives the
  **uncalibrated machine's expected pointing error**.

A result is *not usable* when fewer than half of the parameter directions are determined, or when its
predicted pointing uncertainty (RMS over the grid) is above :data:`USABLE_FRACTION` of the uncalibrated
machine's expected error (RMS). A calibration is made to cut the pointing error by an order of magnitude
or more (the paper's Table 2 machine: 0.8 deg to below 0.01 deg); one whose own uncertainty is a tenth of
the error it should remove cannot deliver that, and compensating with it moves the machine by amounts the
data do not support. Measured (``pmcal twin measure --preset paper-table2 --seed 1``, 24 planned poses):
42 of 55 directions, 0.0042 deg RMS against 3.45 deg uncalibrated; the same pose measured 30 times: 6 of
55 directions, 0.41 deg RMS.

The paper's per-limb model has no prior: its determined directions are the numerical rank of its limbs'
Jacobians (:data:`RANK_TOL`), and no pointing uncertainty is predicted. planar_2dof: the determined
directions are the rank of the identification matrix, and no position uncertainty is predicted: its
recorded covariance is far above the errors its campaigns leave (14 boundary positions, preset group1:
dtheta1 1 sigma 0.73 deg against an actual error of 0.11 deg; propagated, 7.6 mm RMS over W against an
uncalibrated 11.4 mm), so a verdict on it would refuse good calibrations.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy import stats

from pmcal.errors import InputError
from pmcal.fileio import write_json

#: A calibration whose predicted pointing uncertainty (RMS over the grid, 1 sigma) is above this fraction
#: of the uncalibrated machine's expected pointing error (RMS, 1 sigma) is not usable (module docstring).
USABLE_FRACTION = 0.1
#: Relative singular value below which a direction of the paper model's Jacobian counts as not determined
#: (a condition number of 1e6; 24 planned poses give ~1e4, one pose repeated ~1e50).
RANK_TOL = 1e-6
#: The campaign that fixes an unusable calibration (named by warnings and refusals).
CAMPAIGN_FIX = ("measure >= 24 poses spread over the workspace: 'pmcal twin plan --frame tracker --poses 48' "
                "plans them (docs/fullchain.md)")


def judge(determined: int, n_params: int, rms: float | None = None, most: float | None = None,
          uncalibrated: float | None = None, unit: str = "deg", what: str = "pointing") -> dict:
    """The ``quality`` object: the numbers and the verdict (``usable``, ``why``); ``rms``, ``most`` and
    ``uncalibrated`` None when the model predicts no uncertainty (the paper's)."""
    why = []
    if determined < n_params / 2:
        why.append(f"only {determined} of {n_params} parameter directions are determined by the campaign")
    if rms is not None and rms > USABLE_FRACTION * uncalibrated:
        why.append(f"the predicted {what} uncertainty ({rms:.3g} {unit} RMS, 1 sigma) is above "
                   f"{USABLE_FRACTION:g} x the uncalibrated machine's expected error ({uncalibrated:.3g} {unit})")
    return {"determined_directions": determined, "parameters": n_params,
            f"predicted_{what}_std_{unit}": None if rms is None else {"rms": rms, "max": most},
            f"uncalibrated_{what}_error_{unit}": uncalibrated,
            "usable": not why, "why": "; ".join(why) if why else None,
            "note": (f"{what} uncertainty: posterior covariance propagated over the quality grid (1 sigma); "
                     "uncalibrated error: the prior (manufacturing tolerances) propagated the same way; not usable "
                     f"below half the directions determined or above {USABLE_FRACTION:g} x the uncalibrated error "
                     "(RMS over the grid)") if rms is not None else
                    ("determined directions: numerical rank of the identification Jacobian; not usable below half "
                     f"of them; no {what} uncertainty predicted for this model (docs/formats.md)")}


#: A folder machine's campaign needs at least this many readings (3 per measured target, 1 per distance
#: reading) per combination of its structural base set, on distinct poses: fewer determine the errors no
#: better than the prior, whatever the rank says
MIN_READINGS_PER_COMBINATION = 2


#: a folder machine's fit "stops above the noise floor" when its chi-square is beyond what the declared noise
#: gives with this probability and its chi2/dof above :data:`FIT_CHI2_PER_DOF`
FIT_P = 1e-6
FIT_CHI2_PER_DOF = 1.5


def chain_quality(rank: int, reference_rank: int, n_poses: int, distinct_poses: int, readings_per_pose: int,
                  outliers: list[str], fit: dict | None = None, required_rank: int | None = None) -> dict:
    """The ``quality`` object of a folder machine's identification (docs/formats.md, "Campaign quality").

    Parameters
    ----------
    rank : combinations of errors the campaign determines (its base set).
    reference_rank : combinations a campaign spread over the workspace determines (the machine's structural
        base set, :func:`pmcal.chain.reference_basis`).
    n_poses, distinct_poses : rows of the campaign, and how many of them are different poses (a pose measured
        twice counts once).
    readings_per_pose : readings one pose gives (3 per target, or 1 distance).
    outliers : one text per gross outlier found (row, pose, target, how far), empty if none.
    fit : the fit's ``chi2``, ``dof``, ``residual_rms_mm``, ``sigma_mm`` and ``held_out``
        (:func:`pmcal.calib.closed_chain.held_out_check`); None: not judged.
    required_rank : the reference's combinations a campaign must determine (those well above the rank
        tolerance, :meth:`pmcal.calib.closed_chain.BaseSet.clear_rank`); None: all ``reference_rank``.

    Not usable when the campaign determines fewer combinations than the reference requires, when it has fewer
    distinct poses than ``MIN_READINGS_PER_COMBINATION x reference_rank / readings_per_pose``, when it
    holds gross outliers, when the fit stops above the noise floor (chi-square beyond :data:`FIT_P` and
    chi2/dof above :data:`FIT_CHI2_PER_DOF`), or when it does not predict the poses it did not fit.
    """
    needed = -(-MIN_READINGS_PER_COMBINATION * reference_rank // readings_per_pose)
    why = []
    required = reference_rank if required_rank is None else min(int(required_rank), reference_rank)
    if rank < required:
        why.append(f"the campaign determines {rank} of the {required} error combinations a campaign spread "
                   "over the workspace determines")
    if distinct_poses < needed:
        repeated = f" ({n_poses - distinct_poses} rows repeat a pose)" if distinct_poses < n_poses else ""
        why.append(f"{distinct_poses} distinct poses{repeated}, fewer than the {needed} the machine's "
                   f"{reference_rank} combinations need")
    if outliers:
        why.append("gross outlier" + ("s" if len(outliers) > 1 else "") + ": " + "; ".join(outliers)
                   + " (remeasure or delete the row)")
    if fit is not None and not outliers:
        why += _fit_reasons(fit)
    return {"determined_directions": rank, "parameters": reference_rank, "poses": n_poses,
            "distinct_poses": distinct_poses, "poses_needed": needed, "outliers": list(outliers),
            "usable": not why, "why": "; ".join(why) if why else None,
            "note": ("determined directions: the rank of the campaign's base set, of the machine's structural base "
                     "set; not usable below its clear part (directions above 1e-5 of the most visible), below "
                     f"{MIN_READINGS_PER_COMBINATION} readings per combination on distinct poses, or with gross "
                     "outliers (docs/formats.md)")}


def _fit_reasons(fit: dict) -> list[str]:
    """Why a folder machine's fit is not usable although its campaign is: it stops above the noise floor, or it
    does not predict poses it did not fit (:func:`chain_quality`)."""
    out = []
    per_dof = fit["chi2"] / fit["dof"]
    if not np.isfinite(per_dof):
        return ["the fit's residual is not a number: the identified machine does not assemble at every measured "
                "pose (a campaign near a singularity, or on another assembly branch than the model's home)"]
    if per_dof > FIT_CHI2_PER_DOF and stats.chi2.sf(fit["chi2"], fit["dof"]) < FIT_P:
        out.append(f"the fit stops above the noise floor: {fit['residual_rms_mm']:.4f} mm rms left, chi2/dof "
                   f"{per_dof:.2f} for the tracker noise of {fit['sigma_mm']:g} mm (a wrong sigma_mm, an error "
                   "frame missing from [errors], or an effect the geometry does not hold)")
    held = fit.get("held_out") or {}
    if held.get("passed") is False:
        out.append(f"it does not predict poses it did not fit: {held['rms_mm']:.4f} mm rms on held-out poses "
                   f"where {held['predicted_rms_mm']:.4f} mm is predicted (errors fitted as knobs the machine "
                   "does not have)")
    return out


def quality_line(q: dict) -> str:
    """The one-line summary ``identify`` prints, e.g. ``42 of 55 parameter directions determined; predicted
    pointing uncertainty 0.0021 deg RMS, 0.0050 deg max (uncalibrated 0.52 deg)``."""
    line = f"{q['determined_directions']} of {q['parameters']} parameter directions determined"
    key = next(k for k in q if k.startswith("predicted_"))
    if q[key] is None:
        return line
    what, unit = key[len("predicted_"):].split("_std_")
    unc = q[f"uncalibrated_{what}_error_{unit}"]
    return (f"{line}; predicted {what} uncertainty {q[key]['rms']:.2g} {unit} RMS, {q[key]['max']:.2g} {unit} max "
            f"(uncalibrated {unc:.2g} {unit})")


def paper_quality(n_params: int, singular_values) -> dict:
    """The ``quality`` object of a paper-model fit (no prior, no predicted uncertainty): the determined
    directions are the numerical rank of each limb's column-normalised Jacobian (``singular_values``, one
    array per limb), singular values above :data:`RANK_TOL` times the largest."""
    rank = sum(int(np.sum(np.asarray(sv) > RANK_TOL * np.max(sv))) for sv in singular_values if np.size(sv))
    return judge(rank, n_params)


def save_table(table, path, quality: dict | None) -> None:
    """Save a compensation table (JSON and CSV beside it); a table made with ``--force`` from a calibration
    flagged not usable carries its ``quality`` object in the JSON, so ``pmcal push`` refuses it too."""
    table.save(path)
    if isinstance(quality, dict) and quality.get("usable") is False:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
        doc["quality"] = quality
        write_json(path, doc)


def refuse_unusable(doc: dict, path: str, force: bool, fix: str = CAMPAIGN_FIX) -> None:
    """InputError naming ``path`` when the parameters/table document ``doc`` carries ``quality.usable``
    false (written by ``pmcal identify``), unless ``force``."""
    q = doc.get("quality") if isinstance(doc, dict) else None
    if force or not isinstance(q, dict) or q.get("usable", True) is not False:
        return
    raise InputError(f"calibration flagged not usable ({q.get('why') or 'campaign too weak'}): {fix}; or add "
                     "--force to use it anyway", file=path, field="quality")
