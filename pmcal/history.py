"""A machine's calibration history: one JSON record per calibration in a folder, and what moved.

:func:`file_calibration` files an identification's record (:func:`chain_record_document`, or ocpm_2dof's
:func:`pmcal.ocpm.calibration.record_document`) (``pmcal identify ... --history DIR``): date, the campaign
file's SHA-256, every parameter with its standard deviation and 95 % interval, their covariance, the fit
residual and the tracker noise. Records are never overwritten.

:func:`compare` tests which parameters moved between two calibrations. The change of the parameter
vector, ``d = p_last - p_prev``, has covariance ``C = C_prev + C_last`` (independent campaigns). Marginal
tests of ``d_k / sqrt(C_kk)`` have little power: the whole-chain parameters are strongly correlated (a link
length trades against a joint position), so marginal standard deviations are several times what the
data say about a change of one parameter with the others unchanged. And the plain difference of two MAP
estimates carries the priors' pull, which differs between campaigns with different poses. The test
therefore works on what each campaign's data alone say (:func:`data_information`: information ``H_i`` and
``g_i = H_i p_i,data`` of the linearised fit) in one joint model of both campaigns: a machine ``p`` (with
the tolerance prior, shared) and a change ``delta_S`` of the parameters in S between them,
``g_prev ~ N(H_prev p, H_prev)``, ``g_last ~ N(H_last (p + E_S delta_S), H_last)``. Single-parameter
changes are added by forward selection: the parameter whose change lowers the chi-square most is flagged
when the drop exceeds the chi-square(1) quantile at ``alpha / (m - |S|)`` (Bonferroni over the candidates
still in play: at most ``alpha`` family-wise false flags for two calibrations of an unchanged machine);
selection stops at the first that does not pass. Candidates are the parameters both campaigns determine
(:func:`determined`): a parameter held near its design value by its prior cannot be seen to move.
Units: mm and degrees.
"""

from __future__ import annotations

import hashlib
import math

from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
from scipy import stats

from pmcal.errors import InputError, for_option
from pmcal.fileio import check_output, read_json, write_json

#: two-sided 95 % interval half-width in standard deviations
Z95 = float(stats.norm.ppf(0.975))
#: default family-wise false-flag rate of :func:`compare`
ALPHA = 0.05
RECORD_VERSION = 1
#: A parameter whose posterior std is above this fraction of its prior std is "not determined by the
#: campaign": the data moved it little, the prior (manufacturing tolerance) holds it.
UNDETERMINED_FRACTION = 0.7
#: the unit of a parameter fitted on a log scale (ocpm_2dof's stiffness ratio): a nuisance the models share,
#: compared never
LOG_UNIT = "ln"


def sha256(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@dataclass
class Record:
    """One filed calibration (mm, deg): ``names`` and ``value`` (n,), ``cov`` (n, n), ``date`` (UTC)."""

    path: str
    date: datetime
    machine: str
    model: str
    campaign: dict
    names: list[str]
    value: np.ndarray
    cov: np.ndarray
    fit: dict
    noise_mm: float | None
    doc: dict = field(default_factory=dict, repr=False)

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))


def chain_record_document(result, campaign_path: str | Path, machine: str, date: datetime | None = None) -> dict:
    """The history record of a machine folder's identification (a
    :class:`pmcal.calib.closed_chain.ChainIdentResult` made in the machine's structural base set,
    :func:`pmcal.chain.reference_basis`: the campaign's own base set depends on its poses, so two campaigns
    are compared in this one): each base parameter's value, unit and the combination of errors it estimates,
    their covariance, and their prior (``info["prior_covariance"]``: correlated where a base parameter
    regroups dependent errors, :func:`pmcal.calib.closed_chain.base_prior_cov`)."""
    names = list(result.base)
    fit = {"residual_rms_mm": float(result.residual_rms_mm), "chi2_per_dof": float(result.chi2_per_dof),
           "n_poses": int(result.n_poses)}
    doc = make_record(machine, "closed_chain", "lm+tikhonov", "base", campaign_path, names, np.asarray(result.x, float),
                  np.asarray(result.covariance, float), list(result.units), fit, float(result.sigma_mm), date)
    for n in names:
        doc["params"][n]["estimates"] = result.combinations[n]
    prior_cov = np.asarray(result.info["prior_covariance"], float)
    doc.update(prior_std={n: float(s) for n, s in zip(names, np.sqrt(np.diag(prior_cov)))}, prior_mean={},
               prior_covariance={"names": names, "matrix": prior_cov.tolist()})
    return doc


def make_record(machine: str, model: str, method: str, frame: str, campaign_path, names: list[str], value: np.ndarray,
                cov: np.ndarray, units: list[str], fit: dict, noise_mm, date: datetime | None) -> dict:
    """A history record (``RECORD_VERSION``): the parameters ``names`` with their values, units (mm, deg, or
    :data:`LOG_UNIT`), standard deviations and 95 % intervals, their covariance, the fit, the campaign
    file's SHA-256 and the date (now in UTC unless given)."""
    std = np.sqrt(np.diag(cov))
    date = date or datetime.now(timezone.utc)
    return {
        "pmcal_history": RECORD_VERSION, "machine": machine, "model": model, "method": method, "frame": frame,
        "date": date.isoformat(timespec="microseconds"),   # orders two calibrations filed in one second
        "campaign": {"file": str(campaign_path), "sha256": sha256(campaign_path), "n_poses": fit.get("n_poses")},
        "units": {"length": "mm", "angle": "deg"},
        "params": {n: {"value": float(v), "std": float(s), "interval95": [float(v - Z95 * s), float(v + Z95 * s)],
                       "unit": u} for n, v, s, u in zip(names, value, std, units)},
        "covariance": {"names": names, "matrix": cov.tolist()},
        "fit": {k: fit[k] for k in ("residual_rms_mm", "residual_rms_sigma", "chi2_per_dof", "n_poses") if k in fit},
        "tracker_noise_mm": noise_mm,
    }


def file_calibration(record: dict, history_dir: str | Path) -> Path:
    """Write a calibration's record into ``history_dir`` (created if missing); never overwrites.
    ``record``: :func:`chain_record_document` (a machine folder's identification) or
    :func:`pmcal.ocpm.calibration.record_document` (ocpm_2dof's).

    The file is ``YYYYMMDDTHHMMSSZ-<first 8 hex of the campaign SHA-256>.json`` (``-2``, ``-3`` ... when
    taken). Returns its path.

    Examples
    --------
    >>> cal = pmcal.identify(pmcal.read_measurements("m.csv"))             # doctest: +SKIP
    >>> file_calibration(record_document(cal, "m.csv"), "history/cell2")  # doctest: +SKIP
    PosixPath('history/cell2/20261125T101500Z-3fa4c2d1.json')
    """
    doc = record
    folder = Path(history_dir)
    check_history_dir(folder)
    folder.mkdir(parents=True, exist_ok=True)
    stem = datetime.fromisoformat(doc["date"]).strftime("%Y%m%dT%H%M%SZ") + "-" + doc["campaign"]["sha256"][:8]
    path, k = folder / f"{stem}.json", 1
    while path.exists():
        k += 1
        path = folder / f"{stem}-{k}.json"
    write_json(path, doc)
    return path


def check_history_dir(folder: str | Path) -> None:
    """A history folder is a folder (or not there yet) that can be written: checked before any work, so a
    read-only folder does not fail after the parameters file was written (:func:`pmcal.fileio.check_output`:
    its records go inside it, or it is made in a writable folder)."""
    p = Path(folder)
    if p.exists() and not p.is_dir():
        raise InputError("is a file, not a history folder", file=str(p), field="--history")
    with for_option("--history"):
        if p.is_dir():
            check_output(p / "record.json")
        else:
            check_output(p, folder=True)


def read_record(path: str | Path) -> Record:
    """One history record; InputError naming the file and field."""
    p = str(path)
    doc = read_json(path)
    if not isinstance(doc, dict) or "pmcal_history" not in doc:
        raise InputError("not a pmcal history record", file=p, field="pmcal_history")
    try:
        date = datetime.fromisoformat(doc["date"])
    except (KeyError, TypeError, ValueError):
        raise InputError(f"date {doc.get('date')!r} is not an ISO date and time", file=p, field="date") from None
    cov = doc.get("covariance") or {}
    names = cov.get("names")
    try:
        matrix = np.asarray(cov.get("matrix"), float)
    except (TypeError, ValueError):
        matrix = np.zeros(0)
    if not isinstance(names, list) or matrix.shape != (len(names), len(names)) or not np.isfinite(matrix).all():
        raise InputError("covariance must be {names: [...], matrix: n x n finite numbers}", file=p, field="covariance")
    params = doc.get("params") or {}
    value = []
    for n in names:
        v = (params.get(n) or {}).get("value") if isinstance(params.get(n), dict) else None
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise InputError(f"value {v!r} is not a finite number", file=p, field=f"params.{n}")
        value.append(float(v))
    if np.any(np.diag(matrix) < 0):
        raise InputError("negative variance", file=p, field="covariance")
    return Record(path=p, date=date if date.tzinfo else date.replace(tzinfo=timezone.utc),
                  machine=str(doc.get("machine", "")), model=str(doc.get("model", "")), campaign=doc.get("campaign", {}),
                  names=list(names), value=np.array(value), cov=matrix, fit=doc.get("fit", {}),
                  noise_mm=doc.get("tracker_noise_mm"), doc=doc)


def read_history(folder: str | Path) -> list[Record]:
    """Every record (``*.json``) of a history folder, oldest first. InputError if there is none, if the
    folder is missing, or if records of different machines, models or frames are mixed."""
    p = Path(folder)
    if not p.is_dir():
        raise InputError("no such history folder", file=str(p))
    records = sorted((read_record(f) for f in sorted(p.glob("*.json"))), key=lambda r: (r.date, r.path))
    if not records:
        raise InputError("no calibration records (*.json) in the folder; file them with 'pmcal identify ... "
                         "--history DIR'", file=str(p))
    kind = lambda r: (r.machine, r.model, r.doc.get("frame", "base"))  # noqa: E731
    for r in records[1:]:
        if kind(r) != kind(records[0]):
            raise InputError(f"record of {'/'.join(kind(r))} among records of {'/'.join(kind(records[0]))} "
                             "(machine/model/frame: a tracker-frame fit fixes the base frame to the motor axes, a "
                             "base-frame fit to the measured frame; their parameters are not comparable)",
                             file=r.path, field="frame")
    return records


@dataclass
class Change:
    """One parameter between two calibrations (mm or deg).

    ``change`` = last - previous, ``std`` its standard deviation (both covariances), ``z_marginal`` =
    change / std; ``flagged``: selected by :func:`compare`, with ``estimate`` and ``estimate_std`` the
    change the joint fit attributes to it (None when not flagged) and ``p_value`` of its selection step
    (Bonferroni-adjusted)."""

    name: str
    previous: float
    last: float
    change: float
    std: float
    z_marginal: float
    flagged: bool = False
    estimate: float | None = None
    estimate_std: float | None = None
    p_value: float | None = None


def prior_precision(record: Record, names: list[str]) -> np.ndarray:
    """Diagonal prior precision (1/mm^2, 1/deg^2) of the parameters, from the record's prior standard
    deviations (0 where it has none)."""
    full = record.doc.get("prior_covariance")
    if full:                                       # a machine folder's base parameters: a correlated prior
        idx = [full["names"].index(n) for n in names]
        return np.linalg.pinv(np.asarray(full["matrix"], float)[np.ix_(idx, idx)], hermitian=True)
    prior = record.doc.get("prior_std") or {}
    return np.diag([1.0 / prior[n] ** 2 if prior.get(n) else 0.0 for n in names])


def data_information(record: Record, idx: list[int], P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What the campaign's data alone say about the parameters ``idx``: the information ``H = C^-1 - P``
    (posterior precision less the prior's, eigenvalues clipped at 0) and ``g = C^-1 p - P mu``, which for a
    linearised MAP fit with prior mean ``mu`` (0 but for the log stiffness ratio) equals ``H p_data`` (the
    prior's pull removed)."""
    C = record.cov[np.ix_(idx, idx)]
    Ci = np.linalg.pinv(C, hermitian=True)
    w, V = np.linalg.eigh(0.5 * (Ci - P + (Ci - P).T))
    H = (V * np.clip(w, 0.0, None)) @ V.T
    mean = record.doc.get("prior_mean") or {}
    mu = np.array([mean.get(record.names[i], 0.0) for i in idx])
    return H, Ci @ record.value[idx] - P @ mu


def determined(record: Record, name: str) -> bool:
    """The record's campaign determines the parameter: its standard deviation is below
:data:`UNDETERMINED_FRACTION` of its prior (tolerance) standard deviation (True when the
    record has no prior)."""
    prior = (record.doc.get("prior_std") or {}).get(name)
    return prior is None or record.std[record.names.index(name)] < UNDETERMINED_FRACTION * prior


def compare(prev: Record, last: Record, alpha: float = ALPHA) -> list[Change]:
    """Which parameters moved between two calibrations (module docstring: forward selection of
    single-parameter changes in the joint linearised model of both campaigns, family-wise rate ``alpha``).

    Returns one :class:`Change` per parameter the two records share, in the last record's order.

    Examples
    --------
    >>> a, b = read_history("history/cell2")[-2:]                      # doctest: +SKIP
    >>> [c.name for c in compare(a, b) if c.flagged]                   # doctest: +SKIP
    ['L1.dl1']
    """
    if not 0 < alpha < 1:
        raise InputError(f"alpha must be in (0, 1), got {alpha}", field="--alpha")
    names = [n for n in last.names if n in prev.names and same_quantity(prev, last, n)]
    ip, il = [prev.names.index(n) for n in names], [last.names.index(n) for n in names]
    d = last.value[il] - prev.value[ip]
    std = np.sqrt(np.diag(prev.cov[np.ix_(ip, ip)] + last.cov[np.ix_(il, il)]))
    P = prior_precision(last, names)
    H_a, g_a = data_information(prev, ip, P)
    H_b, g_b = data_information(last, il, P)
    m = len(names)
    mu = np.array([(last.doc.get("prior_mean") or {}).get(n, 0.0) for n in names])
    N0 = H_a + H_b + P
    r0 = g_a + g_b + P @ mu                                 # the shared machine under its prior

    def fit(S: list[int]) -> tuple[float, np.ndarray, np.ndarray]:
        """chi2 drop of the change on S, the change (|S|,) and its covariance."""
        E = np.eye(m)[:, S]
        N = np.block([[N0, H_b @ E], [E.T @ H_b, E.T @ H_b @ E]])
        r = np.concatenate([r0, E.T @ g_b])
        sol = np.linalg.lstsq(N, r, rcond=None)[0]
        cov = np.linalg.pinv(N, hermitian=True)[m:, m:]
        return float(r @ sol) - base, sol[m:], cov

    base = float(r0 @ np.linalg.lstsq(N0, r0, rcond=None)[0])
    candidates = [k for k, n in enumerate(names)
                  if unit_of(n, last) != LOG_UNIT and determined(prev, n) and determined(last, n)]
    selected: list[int] = []
    pvals: dict[int, float] = {}
    explained = 0.0
    while len(selected) < len(candidates):
        drops = {k: fit(selected + [k])[0] for k in candidates if k not in selected}
        best = max(drops, key=drops.get)
        p = float(stats.chi2.sf(drops[best] - explained, 1)) * (len(candidates) - len(selected))
        if p > alpha:
            break
        selected.append(best)
        pvals[best] = min(p, 1.0)
        explained = drops[best]
    est, est_std = {}, {}
    if selected:
        _, delta, cov = fit(selected)
        for i, k in enumerate(selected):
            est[k], est_std[k] = float(delta[i]), float(np.sqrt(cov[i, i]))
    return [Change(name=n, previous=float(prev.value[ip[k]]), last=float(last.value[il[k]]), change=float(d[k]),
                   std=float(std[k]), z_marginal=float(d[k] / std[k]) if std[k] > 0 else 0.0,
                   flagged=k in selected, estimate=est.get(k), estimate_std=est_std.get(k), p_value=pvals.get(k))
            for k, n in enumerate(names)]


def _param_field(record: Record, name: str, field: str):
    """``params.<name>.<field>`` of a record, None where absent (the seeded machines' records have no
    ``unit`` or ``estimates``)."""
    return ((record.doc.get("params") or {}).get(name) or {}).get(field)


def estimates(record: Record, name: str) -> str | None:
    """What the parameter ``name`` of a machine folder's record estimates when that is a combination of
    errors (``"platform_1b.dz + 5.236 base.dry - arm1.dz ..."``); None for a plain parameter."""
    text = _param_field(record, name, "estimates")
    return text if text and text != name else None


def same_quantity(a: Record, b: Record, name: str) -> bool:
    """The parameter ``name`` estimates the same quantity in both records: always for the seeded machines;
    for a machine folder's base parameters, the same combination of errors (``params.<name>.estimates``)."""
    return _param_field(a, name, "estimates") == _param_field(b, name, "estimates")


def unit_of(name: str, record: Record) -> str:
    """The record's unit of the parameter: ``mm``, ``deg``, or :data:`LOG_UNIT` (every record carries its
    units)."""
    return _param_field(record, name, "unit") or ""


def history_table(records: list[Record], changes: list[Change] | None) -> tuple[list[str], list[list]]:
    """Rows of ``pmcal history``'s table: parameter, unit, last value, its 95 % half-width, change since the
    previous calibration, its 95 % half-width (marginal), flag, and for a flagged parameter the change the
    test attributes to it with its 95 % half-width."""
    last = records[-1]
    header = ["parameter", "unit", "last", "+-95%", "change", "+-95%", "moved?", "attributed", "+-95%"]
    by_name = {c.name: c for c in changes or []}
    rows = []
    for k, n in enumerate(last.names):
        c = by_name.get(n)
        rows.append([n, unit_of(n, last), float(last.value[k]), float(Z95 * last.std[k]),
                     c.change if c else math.nan, Z95 * c.std if c else math.nan,
                     ("YES" if c.flagged else "no") if c else "–",
                     c.estimate if c is not None and c.flagged else math.nan,
                     Z95 * c.estimate_std if c is not None and c.flagged else math.nan])
    return header, rows


