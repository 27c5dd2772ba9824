"""The exception hierarchy of the appliance.

Every error the appliance raises on purpose derives from :class:`ApplianceError`. Messages name the
thing, the bad value, the rule and the fix, e.g.
``config/appliance.yaml:14: cameras.left.exposure_us = -5: must be > 0``.
"""

from __future__ import annotations


class ApplianceError(Exception):
    """Base class of every error the appliance raises on purpose."""


class ConfigError(ApplianceError):
    """A configuration file is missing, unreadable or does not validate."""


class ManifestError(ApplianceError):
    """A sequence manifest or its frames are unreadable or inconsistent."""


class PatternError(ApplianceError):
    """A pattern sequence is invalid or cannot be decoded (e.g. a missing Gray bit)."""


class DecodeError(ApplianceError):
    """Frames cannot be decoded into projector coordinates."""


class CalibrationError(ApplianceError):
    """A calibration is missing, invalid, or could not be computed."""


class HardwareError(ApplianceError):
    """A device failed, is absent, or answered something unexpected."""


class BackendUnavailableError(HardwareError):
    """An optional backend's library is not installed."""


class CameraError(HardwareError):
    """A camera failed (timeout, lost frame, disconnect)."""


class ProjectorError(HardwareError):
    """A projector failed or refused a command."""


class TriggerError(HardwareError):
    """The trigger controller or GPIO line failed."""


class ScanError(ApplianceError):
    """One scan failed; the service goes on."""


class OutputError(ApplianceError):
    """A cloud, sidecar or preview could not be written."""
