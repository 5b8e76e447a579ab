"""Errors raised by drivers. Each message names the device and its port, and says what to check.

``drivers`` may not import ``rig``; the rig treats :class:`DeviceError` like its own errors (one
line to the user, hardware to its safe state).
"""


class DeviceError(Exception):
    """Root of driver errors: a device misbehaved or could not be reached."""


class DeviceTimeoutError(DeviceError):
    """No (complete) reply within the timeout, after the allowed retries; ``partial``: the bytes
    of an incomplete reply (a device that answered, its reply cut short), empty for silence."""

    def __init__(self, message: str, partial: bytes = b"") -> None:
        super().__init__(message)
        self.partial = partial


class DeviceProtocolError(DeviceError):
    """A reply arrived but is malformed, truncated or does not match the request."""


class DeviceRefusedError(DeviceError):
    """The device answered with an error (a Modbus exception, ``Re-enter``, ``WE OFF``)."""


class DeviceNotFoundError(DeviceError):
    """The port or bus cannot be opened, or the device does not identify as expected."""


class DeviceAbsentError(DeviceRefusedError):
    """A Modbus gateway answered for the device: nothing answers at the unit id asked (Modbus
    exception 10, gateway path unavailable, or 11, gateway target device failed to respond)."""


class LimitError(DeviceError):
    """A set-point outside the device's range or the configured limit was refused before sending."""


class DeviceStateError(DeviceError):
    """A device reads back a state other than the one it was set to (a load not in constant
    current, a relay that did not switch, remote control not taken): nothing more is switched on."""
