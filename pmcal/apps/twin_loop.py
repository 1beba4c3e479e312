"""Twin in the loop, what every machine's loop shares: a strict mock PLC on loopback, the PLC's lookups,
the client links, the error summaries and their printed rows. ocpm_2dof's loop: :mod:`pmcal.apps.ocpm.plc_loop`;
a machine folder's: :mod:`pmcal.apps.chain_loop`.

Units: deg or mm as the machine's motors and task; errors in the unit their keys name.
"""

from __future__ import annotations

import logging
from contextlib import contextmanager

import numpy as np

from pmcal.bridge.errors import BridgeError
from pmcal.bridge.link import PlcLink
from pmcal.bridge.plc_types import LookupResult

#: the version of the table the mock PLC starts with: the controller as commissioned, no calibration
NOMINAL_VERSION = 1


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def error_summary(measured: np.ndarray, true: np.ndarray, unit: str) -> dict:
    """rms and max of errors as the tracker measures them and true ones, keys ``rms_<unit>``, ``max_<unit>``,
    ``true_rms_<unit>``, ``true_max_<unit>`` (what :func:`state_lines` prints)."""
    return {f"rms_{unit}": _rms(measured), f"max_{unit}": float(np.max(measured)),
            f"true_rms_{unit}": _rms(true), f"true_max_{unit}": float(np.max(true))}


def plc_lookup(link: PlcLink, points: np.ndarray, labels: tuple[str, ...]) -> tuple[np.ndarray, int, bool]:
    """What FB_CompTableLookup gives at task points ``points`` (N, A) (the table's axes, in their order and
    units; ``labels`` their columns, for messages): values (N, M) deg / mm, the table version, and whether
    they are corrections to the controller's own nominal IK (a table with nReference 2) or motor commands.
    A failed lookup, or tables switched between lookups, is a :class:`BridgeError`."""
    out, versions, kinds = [], set(), set()
    for x in np.atleast_2d(points):
        res = link.lookup(*(float(v) for v in x))
        if res.result != LookupResult.OK:
            what = getattr(res.result, "name", res.result)
            where = ", ".join(f"{c} {v:g}" for c, v in zip(labels, x))
            raise BridgeError(f"PLC lookup of ({where}) failed: {what}")
        out.append(res.m)
        versions.add(res.table_version)
        kinds.add(res.correction)
    if len(versions) != 1:
        raise BridgeError(f"PLC switched tables during the lookups: versions {sorted(versions)}")
    return np.array(out, float), versions.pop(), kinds.pop()


def default_links(mock, writes):
    """A client link to the started ``mock`` over its own transport, allowed to write ``writes`` (None: what
    a push writes)."""
    from pmcal.bridge.plc_types import PUSH_WRITES

    writes = PUSH_WRITES if writes is None else writes
    if mock.transport == "ads":
        from pmcal.bridge.ads import AdsLink

        return AdsLink(mock.address, writes=writes)
    from pmcal.bridge.modbus import ModbusLink

    return ModbusLink(mock.host, mock.port, rmap=mock.rmap, writes=writes)


@contextmanager
def loopback_mock(transport: str, lifetime_s: float = 600.0):
    """A strict mock PLC (:class:`pmcal.bridge.simulator.ads_mock.AdsMockPlc` or
    :class:`pmcal.bridge.simulator.modbus_mock.ModbusMockPlc`, ``transport`` ``"ads"`` or ``"modbus"``) started on
    127.0.0.1 for the loop, stopped after it; AdsLib's and pymodbus' own logging silenced (one line per
    failure)."""
    from pmcal.bridge.ads import set_adslib_log_level

    set_adslib_log_level(4)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    if transport == "ads":
        from pmcal.bridge.simulator.ads_mock import AdsMockPlc as Mock
    else:
        from pmcal.bridge.simulator.modbus_mock import ModbusMockPlc as Mock
    with Mock(lifetime_s=lifetime_s) as mock:
        yield mock


def state_lines(summary: dict, what: str, unit: str) -> list[str]:
    """The printed rows of a loop's summary: ``what`` (e.g. "pointing error") rms and max as the tracker
    measures it, and the true rms, in ``unit``, before the push, after it and without a table."""
    rows = []
    for name, key in (("before push (nominal table)", "before"), ("after push", "after"),
                      ("compensation without table", "direct_no_table")):
        v = summary[key]
        rows.append(f"  {name:30s} {what} rms {v[f'rms_{unit}']:.4f} {unit}, max {v[f'max_{unit}']:.4f} {unit} "
                    f"(true rms {v[f'true_rms_{unit}']:.4f} {unit})")
    return rows


#: most test targets of a loop
TARGETS_MAX = 10000


def check_target_count(n: int) -> None:
    """``--targets``: 1..:data:`TARGETS_MAX` test targets, else an :class:`pmcal.errors.InputError`."""
    from pmcal.errors import InputError

    if not 1 <= n <= TARGETS_MAX:
        raise InputError(f"targets must be 1..{TARGETS_MAX}, got {n}", field="--targets")
