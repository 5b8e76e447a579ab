"""The one place that talks to pymodbus (pinned to 3.16): both of its error channels - raised
exceptions and error responses - become :mod:`drivers.errors`, with bounded retries.

Every wait runs on the process's clock (:mod:`timebase`, ADR 0038). What pymodbus' synchronous
path times itself is taken over: the serial client's receive loop (:class:`PatientSerialClient`,
which in simulated time waits on the line instead of polling), the TCP client's ``select`` (in
simulated time :class:`SimulatedTcpClient` talks over :mod:`timebase.wires`), the transaction
manager's reply deadline (``monotonic`` of its module, pointed at :func:`timebase.monotonic`, the
same function on the wall clock) and its request lock (a lock of the clock). pymodbus 3.16's
synchronous path keeps no inter-frame silence of its own (no sleep between frames): the serial
client here keeps the RTU line quiet for t3.5 before each request (:func:`rtu_silence_s`)."""

from __future__ import annotations

import logging
from typing import Any

import pymodbus.transaction.transaction as pymodbus_transaction
from pymodbus import FramerType
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

import timebase
from drivers.errors import (
    DeviceAbsentError,
    DeviceError,
    DeviceNotFoundError,
    DeviceProtocolError,
    DeviceRefusedError,
    DeviceTimeoutError,
)
from drivers.transport.serial_port import own_stall_s
from drivers.transport.tty_watch import tty_stall_s, tty_watch

EXCEPTIONS: dict[int, tuple[str, str]] = {
    1: ("illegal function", "the device does not offer this request; check that kind (and regmap)"
        " match the device's model"),
    2: ("illegal data address", "the device has no such register, or it is read-only; check that"
        " kind (and regmap) match the device's model"),
    3: ("illegal data value", "the device refused the value; check it is within the device's own"
        " range and the register map's scale"),
    4: ("server device failure", "the device failed while handling the request; look at its"
        " display for a fault, then switch it off and on"),
    5: ("acknowledge", "the device accepted the request but needs long to carry it out; wait,"
        " then ask again"),
    6: ("server device busy", "the device is busy with a long operation (or its front panel"
        " holds it); close any menu on it and try again"),
    8: ("memory parity error", "the device's memory failed its check; switch it off and on, and"
        " have it serviced if this repeats"),
    10: ("gateway path unavailable", "the gateway has no route for this unit id; check its unit id"
         " mapping and device_id in the rig configuration"),
    11: ("gateway target device failed to respond", "nothing answered the gateway at this unit id;"
         " check device_id in the rig configuration, and the device's power and its cable to the"
         " gateway"),
}  # fmt: skip
"""Modbus exception codes (Modbus Application Protocol V1.1b3, section 7): name and what to check."""
EXCEPTION_NAMES = {code: name for code, (name, _) in EXCEPTIONS.items()}
GATEWAY_CODES = (10, 11)
"""Exceptions a gateway sends for the device behind it: the device itself did not answer."""
ID_FIX = (
    "check the device's Modbus address in the rig configuration (device_id = {id}) against the"
    " one set on the device (its menu or DIP switches show it)"
)


def exception_text(code: int) -> str:
    """``"Modbus exception 3 (illegal data value); the device refused the value; ..."``."""
    name, hint = EXCEPTIONS.get(
        code, ("not a standard code", "see the device's manual for what it means")
    )
    return f"Modbus exception {code} ({name}); {hint}"


logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # errors reach the user through ours

# The synchronous transaction's reply deadline (TransactionManager.sync_get_response) on the
# process's clock: in simulated time a device that keeps sending noise is given up on after the
# timeout in simulated time, not after as much wall time. On the wall clock it is the same clock.
if getattr(pymodbus_transaction, "monotonic", None) is not timebase.monotonic:
    setattr(pymodbus_transaction, "monotonic", timebase.monotonic)  # noqa: B010 - not exported


def _clocked(client: Any) -> None:
    """The lock pymodbus holds across a request, as a lock of the clock (a participant of a
    simulated clock waiting for it lets the holder's exchange run)."""
    client.transaction._sync_lock = timebase.RLock()


RTU_CHARACTER_BITS = 11
"""An RTU character on the line: start, 8 data bits, parity (or a second stop bit without one),
stop (Modbus over Serial Line V1.02, 2.5.1). A line set to 8N1 carries 10: counting 11 only makes
the silence longer, never shorter than a device that counts 11 expects."""
RTU_FIXED_SILENCE_S = 0.00175
"""t3.5 at baud rates above 19200, fixed by the specification (2.5.1.1)."""


def rtu_silence_s(baudrate: int) -> float:
    """t3.5: the silence between two RTU frames (s), 3.5 characters of :data:`RTU_CHARACTER_BITS`
    up to 19200 Bd (4.01 ms at 9600) and :data:`RTU_FIXED_SILENCE_S` above."""
    if baudrate > 19200:
        return RTU_FIXED_SILENCE_S
    return 3.5 * RTU_CHARACTER_BITS / baudrate


def rtu_reply_length(frame: bytes) -> int | None:
    """Length (bytes, CRC included) of the Modbus RTU reply that ``frame`` starts, once its header
    tells it; None while unknown (fewer than 3 bytes, or a function code without a fixed form)."""
    if len(frame) < 2:
        return None
    fc = frame[1]
    if fc & 0x80:
        return 5  # id, fc | 0x80, exception code, CRC
    if fc in (1, 2, 3, 4):
        return 5 + frame[2] if len(frame) >= 3 else None  # id, fc, byte count, data, CRC
    if fc in (5, 6, 15, 16):
        return 8  # the echo of address and value / quantity
    return None


class PatientSerialClient(ModbusSerialClient):
    """pymodbus' serial client whose timeout measures the device, not this computer.

    pymodbus 3.16 polls the receive buffer while a wall-clock window is open, gives up without
    looking again when it has closed, and takes a reply as complete after one quiet poll interval
    (1 ms). On a busy computer a reply can reach the port in pieces with a longer pause between
    them (the kernel hands pty and USB-serial data over in a worker thread), and this process can
    be descheduled past the deadline while the reply arrives: both became timeouts, and the late
    bytes were thrown away before the request was sent again. Here a reply is read until its RTU
    header says it is whole, the buffer is always looked at once more when the time is up, and
    time this process spent descheduled (a poll that overslept) and time the kernel's terminal
    layer held bytes back (:mod:`drivers.transport.tty_watch`) extend the deadline.
    (Overrides ``recv`` of the pinned minor version.)
    """

    heard = False
    """Bytes arrived since the caller last cleared this: the device is alive, the line garbled."""
    _whole = False
    """A reply as long as its header said has been handed over for this request: if pymodbus asks
    for more, it rejected that one (bad CRC), and the device will send nothing else."""

    retrying = False
    """Set by the caller while it sends the same request again after a timeout."""
    _line_used_s: float | None = None
    """When the line last carried a byte (monotonic s): a reply's last byte taken, or the end of
    this client's last request on the line. None: nothing since the port opened."""
    _sent = b""
    _late = b""
    """What arrived after the last attempt gave up and before this retry of the same request: the
    device's late answer to it, taken as this attempt's reply if it is one."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        _clocked(self)

    def connect(self) -> bool:
        """Open the port, with no write timeout: pyserial checks it after the bytes are out, so
        a process stopped or descheduled just after writing a request raised 'Write timeout' on
        resuming, and the retry's reopen threw the device's answer away (a request is a few
        bytes, which the kernel takes at once)."""
        ok = bool(super().connect())
        if ok and self.socket is not None and getattr(self.socket, "write_timeout", None):
            self.socket.write_timeout = None
        return ok

    def send(self, request: bytes, addr: tuple[str, int] | None = None) -> int:
        self._whole = False
        late = self._keep_silence()  # what came meanwhile: pymodbus would throw it away
        # A reply that came after the deadline answers the same request, not a different one: on
        # a busy computer (the simulator on the same cores) every reply can come a little late,
        # and throwing each away before the retry turned a slow device into a silent one.
        self._late = late if self.retrying and request == self._sent else b""
        self._sent = request
        if self._late:
            # not sent again: the device is answering the first one, and a second copy would
            # get a second answer that lands on the next request
            return len(request)
        sent = int(super().send(request, addr))
        # its last bit leaves the UART this long after the write (the UART's queue was empty)
        self._line_used_s = timebase.monotonic() + self._character_s() * len(request)
        return sent

    def _character_s(self) -> float:
        return RTU_CHARACTER_BITS / float(self.comm_params.baudrate or 9600)

    def _keep_silence(self) -> bytes:
        """Wait until the line has been quiet for t3.5 since it last carried a byte (a byte that
        comes meanwhile starts the quiet again); returns what came. The quiet is the line's:
        time the kernel's terminal layer may have held bytes back is not counted (ADR 0013). A
        line that never falls quiet is given up on after the reply timeout: the request goes,
        as pymodbus would send it, and its reply decides."""
        if self.socket is None:
            return b""
        got = b""
        if waiting := int(self.socket.in_waiting):
            got = self.socket.read(waiting)
            self._line_used_s = timebase.monotonic()
        if self._line_used_s is None:
            return got
        t35 = rtu_silence_s(int(self.comm_params.baudrate or 9600))
        give_up = timebase.monotonic() + max(float(self.comm_params.timeout_connect or 0), t35)
        wait_readable = getattr(self.socket, "wait_readable", None)
        while True:
            now = timebase.monotonic()
            quiet_at = self._line_used_s + t35 + tty_stall_s(self._line_used_s, now)
            if now >= quiet_at or now >= give_up:
                return got
            if wait_readable is None:
                timebase.sleep(quiet_at - now)  # a byte arriving meanwhile is seen next round
            else:
                wait_readable(quiet_at - now)
            if waiting := int(self.socket.in_waiting):
                got += self.socket.read(waiting)
                self._line_used_s = timebase.monotonic()

    def recv(self, size: int | None) -> bytes:
        if not self.socket:
            raise ConnectionException(str(self))
        start = last = timebase.monotonic()
        window = QUIET_AFTER_WHOLE_S if self._whole else float(self.comm_params.timeout_connect)
        deadline = last + window
        buf, self._late = self._late, b""
        if buf:
            self.heard = True
        quiet_since = last
        # a simulated line (simpipe://) is waited on; a real port is looked at every interval
        wait_readable = getattr(self.socket, "wait_readable", None)
        try:
            while True:
                waiting = int(self.socket.in_waiting)
                if waiting:
                    buf += self.socket.read(waiting)
                    quiet_since = self._line_used_s = timebase.monotonic()
                    self.heard = True
                need = size if size is not None else rtu_reply_length(buf)
                if buf and need is not None and len(buf) >= need:
                    self._whole = size is None
                    return buf
                now = timebase.monotonic()
                if buf and need is None and now - quiet_since > QUIET_UNKNOWN_S:
                    return buf  # a reply of no known form, quiet for a while: let pymodbus judge
                # whatever kept this loop from looking for longer than one poll was us, not the
                # device (descheduled, stopped, waiting for the interpreter lock)
                deadline += own_stall_s(now - last, self._recv_interval)
                last = now
                if now >= deadline + tty_stall_s(start, now):
                    return buf
                if wait_readable is None:
                    timebase.sleep(self._recv_interval)
                    continue
                # until a byte comes, the deadline or (a reply of no known form) the first look
                # after its quiet time, as the polling loop would look
                wake = deadline
                if buf and need is None:
                    wake = min(wake, quiet_since + QUIET_UNKNOWN_S + self._recv_interval)
                wait_readable(wake - now)
        except OSError:
            self.close()  # type: ignore[no-untyped-call]
            raise ConnectionException(str(self)) from None


class SimulatedTcpClient(ModbusTcpClient):
    """pymodbus' TCP client on the simulated loopback network (:mod:`timebase.wires`), for
    simulated time: ``connect`` opens a pipe to the simulated server at host and port (refused
    when none listens there), and ``recv`` keeps pymodbus' contract with waits on the clock (the
    first bytes to arrive within the timeout when ``size`` is None, else up to ``size`` bytes
    within it; a peer that closed gives what came before, else ConnectionException)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.socket: Any = None  # a timebase.wires.PipeEnd once connected
        _clocked(self)

    def connect(self) -> bool:
        if self.socket:
            return True
        from timebase.wires import wires

        try:
            self.socket = wires().connect(str(self.comm_params.host), int(self.comm_params.port))
        except OSError:
            self.close()
        return self.socket is not None

    def close(self) -> None:
        if self.socket:
            self.socket.close()
        self.socket = None

    def send(self, request: bytes, addr: tuple[str, int] | None = None) -> int:
        if not self.socket:
            raise ConnectionException(str(self))
        if not request:
            return 0
        try:
            return int(self.socket.write(request))
        except OSError:
            self.close()
            raise ConnectionException(str(self)) from None

    def recv(self, size: int | None) -> bytes:
        if not self.socket:
            raise ConnectionException(str(self))
        end, start = self.socket, timebase.monotonic()
        timeout = float(self.comm_params.timeout_connect or 0)
        if size is None:
            data = end.read_available(4096) if end.wait_readable(timeout) else b""
        else:
            data = end.read(size, timeout)
        if end.peer_closed and (not data or (size is not None and len(data) < size)):
            got = [data] if data else []
            return bytes(self._handle_abrupt_socket_close(size, got, timebase.monotonic() - start))
        return bytes(data)


GARBLED_EXTRA_ATTEMPTS = 3
"""Attempts added when every reply so far came back damaged (the device is there; the line is
noisy): with 10 % bad CRCs a request then fails once in 10^6, not once in 10^3."""
QUIET_AFTER_WHOLE_S = 0.02
"""After a whole reply was rejected (bad CRC), how long to look for anything more before calling
the attempt failed (s): a device answers once per request, so the full timeout would be waste."""
QUIET_UNKNOWN_S = 0.05
"""A reply whose length its header does not give is complete after this long without a byte (s)."""


class ModbusLink:
    """A Modbus device on TCP (``host``/``port``) or RTU (``path``: a device or pyserial URL).

    Requests that time out or come back garbled are retried ``retries`` times; a Modbus exception
    reply is never retried (the device answered: repeating the request would not change it).
    """

    def __init__(
        self,
        *,
        name: str,
        host: str | None = None,
        port: int = 502,
        path: str | None = None,
        baudrate: int = 115200,
        parity: str = "N",
        device_id: int = 1,
        timeout_s: float = 0.5,
        retries: int = 2,
    ) -> None:
        if (host is None) == (path is None):
            raise ValueError("give exactly one of host (Modbus TCP) and path (Modbus RTU)")
        self.name = name
        self.device_id = device_id
        self.retries = retries
        self.where = f"{host}:{port}" if host is not None else f"{path}"
        self.tcp = host is not None
        self.line = f"baud rate {baudrate}, parity {parity}"
        self.answered = False  # the device has answered since this link was made: its id is right
        self._lock = timebase.RLock()  # held across a request: a lock of the clock
        self.failed = False  # the last request went unanswered: try once, not retries + 1 times
        self.stale_replies = 0  # replies to an earlier request, recognized by their size
        self._client: Any
        if host is not None:
            # in simulated time the devices are on the simulated loopback network
            tcp = SimulatedTcpClient if timebase.is_simulated() else ModbusTcpClient
            self._client = tcp(host, port=port, timeout=timeout_s, retries=0)
        else:
            assert path is not None
            tty_watch()
            self._client = PatientSerialClient(
                path,
                framer=FramerType.RTU,
                baudrate=baudrate,
                parity=parity,
                timeout=timeout_s,
                retries=0,
            )
        self.connect()

    def connect(self) -> None:
        """(Re)open the connection."""
        try:
            ok = self._client.connect()
        except (ModbusException, OSError) as exc:
            ok = False
            detail = f" ({exc})"
        else:
            detail = ""
        if not ok:
            raise DeviceNotFoundError(
                f"{self.name}: cannot connect to Modbus device at {self.where}{detail};"
                " check power, cable, address and port"
            )

    def _call(self, what: str, fn: Any, *args: Any, **kwargs: Any) -> Any:
        with self._lock:  # one request at a time per link, whichever thread asks
            return self._call_locked(what, fn, *args, **kwargs)

    def _call_locked(self, what: str, fn: Any, *args: Any, **kwargs: Any) -> Any:
        last: Exception | None = None
        attempts = 1 if self.failed else self.retries + 1
        self._client.heard = False
        attempt = -1
        while True:
            attempt += 1
            if attempt >= attempts:
                # a device that answers, garbled, is alive: give it a few more tries (each costs
                # QUIET_AFTER_WHOLE_S, not a timeout) before giving up on this request
                garbled_attempts = self.retries + 1 + GARBLED_EXTRA_ATTEMPTS
                if not getattr(self._client, "heard", False) or attempts >= garbled_attempts:
                    break
                attempts = garbled_attempts
            self._client.retrying = attempt > 0
            try:
                if not self._client.connected:
                    self.connect()
                rr = fn(*args, device_id=self.device_id, **kwargs)
            except (ConnectionException, OSError) as exc:  # refused, reset, broken pipe, pty gone
                last = exc
                self._client.close()
                continue
            except ModbusIOException as exc:
                last = exc
                continue
            except ModbusException as exc:
                last = exc
                timebase.sleep(0.05 * (attempt + 1))  # let a garbled line settle before retrying
                continue
            self.failed = False
            return self._answer(what, rr)
        raise self._gave_up(what, attempts, last)

    def _answer(self, what: str, rr: Any) -> Any:
        """A reply: returned, or its exception code raised as the device's refusal (or, 10 and
        11, as a gateway's word that the device behind it is absent)."""
        if rr.isError():
            code = int(getattr(rr, "exception_code", 0))
            if code in GATEWAY_CODES:
                raise self._gateway_error(what, code)
            self.answered = True
            raise DeviceRefusedError(
                f"{self.name} at {self.where} refused {what}: {exception_text(code)}"
            )
        self.answered = True
        return rr

    def _gave_up(self, what: str, attempts: int, last: Exception | None) -> DeviceError:
        """The error after ``attempts`` tries of ``what`` that all failed, the last with ``last``."""
        # garbled replies are a noisy line, not a dead device: the next request gets every retry
        garbled = bool(getattr(self._client, "heard", False))
        self.failed = not garbled
        if isinstance(last, ConnectionException | DeviceNotFoundError | OSError):
            return DeviceNotFoundError(
                f"{self.name} at {self.where}: connection lost during {what} ({last});"
                " check power and cable"
            )
        if isinstance(last, ModbusIOException) and garbled:
            return DeviceProtocolError(
                f"{self.name} at {self.where}: no valid reply to {what} after {attempts}"
                f" attempt{'s' if attempts > 1 else ''}, only damaged ones (bad CRC or cut"
                " short); check for noise on the line: cable shield, termination, baud rate"
            )
        if isinstance(last, ModbusIOException):
            detail = str(last).split(", continue")[0].removeprefix("Modbus Error: ")
            return DeviceTimeoutError(self._silence(what, attempts, detail))
        return DeviceProtocolError(
            f"{self.name} at {self.where}: malformed reply to {what} after {attempts}"
            f" attempts ({last}); check for noise on the line or a wrong framing"
        )

    def _gateway_error(self, what: str, code: int) -> DeviceAbsentError:
        """Exception 10 or 11: a gateway speaks for a device that did not answer."""
        name = EXCEPTION_NAMES[code]
        uid = self.device_id
        if code == 11 and self.answered:
            return DeviceAbsentError(
                f"{self.name} at {self.where}: the device with unit id {uid} stopped answering"
                f" behind the gateway (Modbus exception 11, {name}, to {what}); check its power"
                " and its cable to the gateway"
            )
        return DeviceAbsentError(
            f"{self.name} at {self.where}: no device with unit id {uid} answers (the gateway"
            f" replied Modbus exception {code}, {name}, to {what}); {ID_FIX.format(id=uid)}"
            + (", and the gateway's unit id mapping" if code == 10 else
               ", then the device's power and its cable to the gateway")
        )  # fmt: skip

    def _silence(self, what: str, attempts: int, detail: str) -> str:
        """The message for no reply: on a link that has never had one, name the device id."""
        head = f"{self.name} at {self.where}"
        tried = f"no reply to {what} after {attempts} attempt{'s' if attempts > 1 else ''}"
        if "No response received" not in detail:  # pymodbus' words for silence add nothing
            tried += f" ({detail.removeprefix('[Input/Output] ')})"
        if self.answered:
            return f"{head}: {tried}; it answered before: check its power and cable"
        uid = self.device_id
        if self.tcp:
            return (
                f"{head}: {tried}; a device or gateway may ignore a request for a unit id it does"
                f" not serve: {ID_FIX.format(id=uid)}, then power and network"
            )
        return (
            f"{head}: no device with unit id {uid} answers ({tried}; an RS-485 device stays"
            f" silent when the id is not its own); {ID_FIX.format(id=uid)}, then {self.line},"
            " power and cable"
        )

    def read_registers(self, address: int, count: int = 1) -> list[int]:
        """Holding registers (function 3)."""
        what = f"reading {count} register(s) at {address}"
        for _ in range(2):
            rr = self._call(what, self._client.read_holding_registers, address, count=count)
            regs = list(rr.registers)
            if len(regs) == count:
                return regs
            # RTU replies carry no transaction id: a reply of another size is a late answer to an
            # earlier request. Ask again (the next request first clears what is waiting).
            self.stale_replies += 1
        raise DeviceProtocolError(
            f"{self.name} at {self.where}: asked for {count} registers at {address}, got"
            f" {len(regs)} twice; check that nothing else talks on this bus"
        )

    def write_register(self, address: int, value: int) -> None:
        """One holding register (function 6)."""
        self._call(
            f"writing {value} to register {address}", self._client.write_register, address, value
        )

    def write_registers(self, address: int, values: list[int]) -> None:
        """Several holding registers (function 16)."""
        self._call(f"writing {len(values)} registers at {address}", self._client.write_registers,
                   address, values)  # fmt: skip

    def read_coils(self, address: int, count: int = 1) -> list[bool]:
        """Coils (function 1): ``count`` states, the first at ``address`` (a reply's padding bits
        past ``count`` are dropped: some devices fill them with noise)."""
        rr = self._call(f"reading {count} coil(s) at {address}", self._client.read_coils,
                        address, count=count)  # fmt: skip
        bits = [bool(b) for b in rr.bits]
        if len(bits) < count:
            raise DeviceProtocolError(f"{self.name} at {self.where}: asked for {count} coils at"
                                      f" {address}, got {len(bits)}")  # fmt: skip
        return bits[:count]

    def write_coil(self, address: int, on: bool) -> None:
        """One coil (function 5): 0xFF00 for on, 0x0000 for off."""
        self._call(f"writing {'on' if on else 'off'} to coil {address}", self._client.write_coil,
                   address, bool(on))  # fmt: skip

    def close(self) -> None:
        """Close the connection."""
        self._client.close()
