"""Failures of a transfer to the PLC, each with a one-line message and the CLI exit status.

Only :class:`LinkError` (and its :class:`ReadbackMismatch`) is retried: the link is closed, reopened
and the transfer restarts from the interface check. Everything else stops at once. Bad tables and
stale versions are :class:`pmcal.errors.InputError` (exit 2) and are raised before any write.
"""

from __future__ import annotations


class BridgeError(Exception):
    """A transfer failed. ``exit_status`` is what ``pmcal push`` returns."""

    exit_status = 1


class LinkError(BridgeError):
    """The connection failed (refused, dropped, time-out): close, reopen and restart the transfer."""


class ReadbackMismatch(LinkError):
    """What the PLC holds after staging differs from what was sent: restart the transfer."""


class DeviceError(BridgeError):
    """The PLC answered a request with an error (ADS error code / Modbus exception): no retry."""


class InterfaceError(BridgeError):
    """The PLC does not offer the expected interface (not in RUN, symbol type/size, register map)."""


class Rejected(BridgeError):
    """The PLC checked the committed table and refused it (its status code says why): no retry."""

    exit_status = 3


class StagingBusy(BridgeError):
    """Another client owns the PLC's staging area (nStagingOwner is not our session token): no retry."""


class AckTimeout(BridgeError):
    """The PLC did not acknowledge the commit in time; the commit was withdrawn."""


class WriteNotAllowed(BridgeError):
    """A write outside the client's allow-list was attempted (a programming error; nothing sent)."""
