"""One error hierarchy for telesurg, rooted in :class:`TelesurgError`."""

from __future__ import annotations


class TelesurgError(Exception):
    """Base class of every error telesurg raises on purpose."""


class MessageError(TelesurgError, ValueError):
    """A payload could not be decoded or failed validation (type, shape, finite, size, version)."""


class ConfigError(TelesurgError, ValueError):
    """A configuration file or command-line override is invalid; the message names valid options."""


class KinematicsError(TelesurgError, ValueError):
    """A kinematic computation has no valid answer."""


class IKError(KinematicsError):
    """Inverse kinematics failed: target unreachable, singular, or every branch violates a limit."""


class SiteStartError(TelesurgError, RuntimeError):
    """A local site (``telesurg up`` / ``demo``) could not start: its router's port is taken, a
    service did not come up; nothing of it is left running."""


class DeviceConnectionError(TelesurgError, ConnectionError):
    """A device (serial port, simulator) could not be reached or stopped answering."""


class AuthorityError(TelesurgError, PermissionError):
    """An operator command, e-stop or reset refused by the operator authority (shared/authority.py);
    the message is the reason the sender is told."""
