"""The Modbus devices in simulated time (ADR 0038): synchronous servers on the simulated clock's
wires, in place of the asyncio loop, pymodbus' servers and the proxies of :mod:`sim.async_modbus`.

A Modbus TCP endpoint listens on the clock's loopback network (``wires().listen``) and serves each
connection with one thread of the clock; a Modbus RTU device serves its line
(``simpipe://<name>``) with one thread. A thread waits for request bytes on the clock, frames them
with pymodbus' own framers, runs the request's ``datastore_update`` coroutine on a ``SimCore`` of
the devices to its end (it never truly awaits: the models' fault delays sleep on the clock) and
writes the reply frame, as pymodbus' ``ServerRequestHandler`` does.

Kept from the wall clock's path: a TCP endpoint answers exception 11 for unit ids it does not serve
(:func:`sim.modbus_devices.unserved_ids`); an RTU device stays silent for requests to other ids
and frames requests by their length (:func:`sim.transports.rtu_request_length`, a partial request older
than :data:`sim.transports.STALE_PARTIAL_S` dropped); and the link faults of :class:`sim.transports.TcpProxy`
and :class:`sim.transports.PtyNullModem`: replies dropped or corrupted (:func:`sim.transports.damage`, a
seeded generator per endpoint), delayed, none while silent; while ``disconnect`` a new TCP
connection is closed at once and an open one at its next request, and an RTU line takes nothing.
"""

from __future__ import annotations

import contextlib
import random
from collections.abc import Coroutine
from typing import TYPE_CHECKING, Any

from pymodbus import FramerType
from pymodbus.constants import ExcCodes
from pymodbus.exceptions import ModbusIOException, NoSuchIdException
from pymodbus.framer import FRAMER_NAME_TO_CLASS
from pymodbus.pdu import DecodePDU, ExceptionResponse, ModbusPDU
from pymodbus.simulator import SimDevice
from pymodbus.simulator.simcore import SimCore

import timebase
from sim.modbus_devices import NoReply
from sim.modbus_requests import QUANTITY_CHECKED
from sim.physics import Faults
from sim.transports import STALE_PARTIAL_S, damage, rtu_request_length

if TYPE_CHECKING:
    import threading

    from timebase.wires import PipeEnd

MAX_BUFFER = 516
"""Bytes a TCP connection keeps while no request frame fits them (pymodbus' own limit)."""


def run_to_end(coro: Coroutine[Any, Any, Any]) -> Any:
    """The result of a coroutine that never awaits anything that suspends it (a datastore update
    whose model sleeps on the simulated clock, not on an event loop)."""
    try:
        coro.send(None)
    except StopIteration as done:
        return done.value
    coro.close()
    raise RuntimeError("a Modbus datastore update awaited an event loop in simulated time")


class Answerer:
    """pymodbus' request handling without its server: frame, execute on the devices, reply."""

    def __init__(self, devices: list[SimDevice], framer: FramerType) -> None:
        self.core = SimCore(devices)
        decoder = DecodePDU(True)
        for request in QUANTITY_CHECKED:  # a quantity out of range is exception 3, as pymodbus'
            decoder.register(request)  # server with custom_pdu answers it
        self.framer = FRAMER_NAME_TO_CLASS[framer](decoder)

    def split(self, buf: bytes) -> tuple[int, ModbusPDU | None, bytes | None]:
        """Frame the start of ``buf``: (bytes used, 0 while the frame is incomplete; the request;
        or a reply due at once: exception 1 for a request that does not decode)."""
        try:
            used, pdu = self.framer.handleFrame(buf, 0, 0)
        except ModbusIOException as exc:
            refused = ExceptionResponse(0 if exc.fcode is None else exc.fcode,
                                        exception_code=ExcCodes.ILLEGAL_FUNCTION,
                                        device_id=exc.dev_id, transaction=exc.transaction_id)  # fmt: skip
            return len(buf), None, self.framer.buildFrame(refused)
        return used, pdu, None

    def answer(self, request: ModbusPDU) -> bytes | None:
        """The reply frame to ``request`` (None: none, a silent device)."""
        try:
            response = run_to_end(request.datastore_update(self.core, request.dev_id))  # type: ignore[arg-type]
        except NoReply:
            return None
        except NoSuchIdException:
            response = ExceptionResponse(request.function_code, ExcCodes.GATEWAY_NO_RESPONSE)
        except Exception:  # as pymodbus' handler: any error in the datastore is a device failure
            response = ExceptionResponse(request.function_code, ExcCodes.DEVICE_FAILURE)
        response.transaction_id = request.transaction_id
        response.dev_id = request.dev_id
        return bytes(self.framer.buildFrame(response))

    def answer_frames(self, buf: bytes) -> tuple[bytes, list[bytes]]:
        """Every request frame at the start of ``buf`` answered: (what is left, the replies)."""
        replies: list[bytes] = []
        while buf:
            used, request, at_once = self.split(buf)
            if used == 0:
                break
            buf = buf[used:]
            reply = at_once if request is None else self.answer(request)
            if reply is not None:
                replies.append(reply)
        return buf, replies


class PipeModbus:
    """The Modbus servers of one cage on the current simulated clock (``seed``: the links' fault
    draws, one generator per endpoint)."""

    def __init__(self, seed: int) -> None:
        from timebase.wires import wires

        self.seed = seed
        self._wires = wires()
        self._stop = timebase.Event()
        self._ports: list[int] = []
        self._lines: list[str] = []
        self._connections: dict[str, list[PipeEnd]] = {}
        self._threads: list[threading.Thread] = []

    def _start(self, name: str, target: Any, *args: Any) -> None:
        thread = timebase.Thread(target, name=name, args=args, daemon=True)
        self._threads.append(thread)
        thread.start()

    # --- Modbus TCP -----------------------------------------------------------------------------

    def serve_tcp(self, name: str, devices: list[SimDevice], faults: Faults) -> int:
        """Serve ``devices`` (one endpoint) on the clock's loopback network; returns the port."""
        answerer = Answerer(devices, FramerType.SOCKET)
        rng = random.Random(self.seed)
        open_ends = self._connections.setdefault(name, [])

        def accept(end: PipeEnd) -> None:
            if faults.disconnect or self._stop.is_set():
                end.close()
                return
            open_ends.append(end)
            self._start(f"modbus-tcp-{name}", self._serve_connection, end, answerer, faults, rng)

        port = self._wires.listen("127.0.0.1", 0, accept)
        self._ports.append(port)
        return port

    def _serve_connection(self, end: PipeEnd, answerer: Answerer, faults: Faults,
                          rng: random.Random) -> None:  # fmt: skip
        buf = b""
        try:
            while not self._stop.is_set() and not end.closed:
                end.wait_readable(None)  # a request, the client's hang-up or stop()'s close
                data = end.read_available()
                if not data or faults.disconnect:
                    return  # the client hung up, or the link drops it at this request
                buf, replies = answerer.answer_frames(buf + data)
                if len(buf) > MAX_BUFFER:
                    buf = b""
                for reply in replies:
                    if not self._reply_tcp(end, reply, faults, rng):
                        return
        finally:
            end.close()
            for ends in self._connections.values():
                if end in ends:
                    ends.remove(end)

    @staticmethod
    def _reply_tcp(end: PipeEnd, reply: bytes, faults: Faults, rng: random.Random) -> bool:
        """Send a reply through the link's faults; False: the connection is to be closed."""
        if faults.disconnect:
            return False
        if faults.silent:
            return True
        if faults.reply_delay_s > 0:
            timebase.sleep(faults.reply_delay_s)
        try:
            end.write(damage(reply, faults, rng))
        except BrokenPipeError:
            return False
        return True

    def drop_connections(self, name: str) -> None:
        """Close the open TCP connections of device ``name`` now."""
        for end in list(self._connections[name]):
            end.close()

    # --- Modbus RTU -----------------------------------------------------------------------------

    def serve_rtu(self, name: str, device: SimDevice, device_id: int, baudrate: int,
                  faults: Faults) -> str:  # fmt: skip
        """Serve ``device`` as Modbus RTU on line ``name`` at ``baudrate``; returns its URL."""
        line = self._wires.serve_serial(name, baudrate)
        self._lines.append(name)
        answerer = Answerer([device], FramerType.RTU)
        rng = random.Random(self.seed)
        self._start(f"modbus-rtu-{name}", self._serve_line, line.device, answerer, device_id,
                    faults, rng)  # fmt: skip
        return line.url

    def _serve_line(self, end: PipeEnd, answerer: Answerer, device_id: int, faults: Faults,
                    rng: random.Random) -> None:  # fmt: skip
        pending, since = b"", 0.0
        while not self._stop.is_set() and not end.closed:
            end.wait_readable(None)  # a request, the client's closing or stop()'s close
            data = end.read_available()
            if not data:  # the client closed the port: nothing comes until it opens it again
                end.wait_peer_open(None)  # (or stop() closes the line)
                continue
            if faults.disconnect or faults.silent:
                pending = b""
                continue
            now = timebase.monotonic()
            if pending and now - since > STALE_PARTIAL_S:
                pending = b""  # a request the client never finished
            if not pending:
                since = now
            pending += data
            while size := rtu_request_length(pending):
                if len(pending) < size:
                    break  # the rest of the request is still on its way
                frame, pending = pending[:size], pending[size:]
                since = now
                if frame[0] == device_id:  # else another station's: the bus stays silent
                    self._reply_rtu(end, answerer.answer_frames(frame)[1], faults, rng)

    @staticmethod
    def _reply_rtu(end: PipeEnd, replies: list[bytes], faults: Faults,
                   rng: random.Random) -> None:  # fmt: skip
        for reply in replies:
            if faults.disconnect or faults.silent:
                return
            out = damage(reply, faults, rng)
            if not out:
                continue
            if faults.reply_delay_s > 0:
                timebase.sleep(faults.reply_delay_s)
            with contextlib.suppress(BrokenPipeError):
                end.write(out)

    # --- the end --------------------------------------------------------------------------------

    def stop(self) -> None:
        """Stop listening, close every connection and line, and join the server threads."""
        self._stop.set()
        for port in self._ports:
            self._wires.unlisten("127.0.0.1", port)
        for name in list(self._connections):
            self.drop_connections(name)
        for name in self._lines:
            self._wires.remove_serial(name)
        for thread in self._threads:
            thread.join(timeout=5.0)
        self._ports.clear()
        self._lines.clear()
        self._threads.clear()
