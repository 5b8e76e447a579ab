"""pyserial URL handler ``simpipe://<name>``: a serial port on a simulated line (timebase.wires).

pyserial finds it by this module's name (``serial.protocol_handler_packages`` holds "timebase").
Reads follow pyserial's timeout rules on the simulated clock.
"""

from __future__ import annotations

from typing import Any

from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from timebase.wires import SCHEME, PipeEnd, wires


class Serial(SerialBase):  # type: ignore[misc]
    """pyserial's port interface over a simulated serial line."""

    _end: PipeEnd | None = None
    is_open: bool = False

    def open(self) -> None:
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        if self.is_open:
            raise SerialException("Port is already open.")
        name = str(self.portstr)
        if not name.startswith(SCHEME):
            raise SerialException(f"expected a URL of the form {SCHEME}<name>, got {name!r}")
        try:
            self._end = wires().open_serial(name[len(SCHEME) :])
        except KeyError:
            raise SerialException(
                f"could not open port {name}: no simulated line of that name"
            ) from None
        self.is_open = True
        self._reconfigure_port()

    def _reconfigure_port(self) -> None:
        if self._end is not None:
            self._end.client_baud = int(self._baudrate)

    def close(self) -> None:
        if self._end is not None:
            self._end.close()
        self._end = None
        self.is_open = False

    def _live(self) -> PipeEnd:
        if not self.is_open or self._end is None:
            raise PortNotOpenError()
        if self._end.peer_closed:
            raise SerialException(f"{self.portstr}: the device is gone")
        return self._end

    @property
    def in_waiting(self) -> int:
        return self._live().in_waiting

    def read(self, size: int = 1) -> bytes:
        return self._live().read(size, self._timeout)

    def write(self, data: Any) -> int:
        try:
            return self._live().write(bytes(data))
        except BrokenPipeError as exc:
            raise SerialException(str(exc)) from None

    def wait_readable(self, timeout_s: float | None) -> bool:
        """Wait on the simulated clock until a byte arrives (True) or ``timeout_s`` passes."""
        return self._live().wait_readable(timeout_s)

    def flush(self) -> None:
        pass

    def reset_input_buffer(self) -> None:
        self._live().discard_input()

    def reset_output_buffer(self) -> None:
        pass

    def send_break(self, duration: float = 0.25) -> None:
        pass

    def _update_break_state(self) -> None:
        pass

    def _update_rts_state(self) -> None:
        pass

    def _update_dtr_state(self) -> None:
        pass

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True
