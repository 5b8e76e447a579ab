"""Real transports for the simulated devices: pseudo-terminals and loopback TCP, with link faults.

* :func:`open_pty` - one raw pty pair: the device holds the master, the client opens the path.
* :class:`PtyNullModem` - two pty pairs joined on an asyncio loop, for servers that must open a
  path themselves (pymodbus' serial server); it can drop, corrupt or delay what the device sends
  and ignores requests to other bus addresses (an RS-485 bus stays silent).
* :class:`TcpProxy` - a loopback TCP front for a server, with the same faults and disconnects.

These are the wall clock's. In simulated time (ADR 0038) the serial devices use lines of the
simulated clock (:mod:`sim.serial_line`) and the Modbus servers of :mod:`sim.pipe_modbus` keep
the faults and the RTU framing rules defined here.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import random
import tty
from dataclasses import dataclass

import timebase
from sim.physics import Faults


@dataclass
class Pty:
    """A raw pseudo-terminal: ``master`` fd for the device, ``path`` for the client."""

    master: int
    slave: int
    path: str

    def close(self) -> None:
        """Close both ends, once: a second call must not close what now has the same numbers
        (the next simulator's ptys in the same process)."""
        for fd in (self.master, self.slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self.master = self.slave = -1


def open_pty() -> Pty:
    """A raw pty pair (no echo, no CR/LF translation). Keep ``slave`` open: it keeps the master
    readable while no client has the path open."""
    master, slave = os.openpty()
    tty.setraw(slave)
    tty.setraw(master)
    os.set_blocking(master, False)  # a full buffer loses data (as a UART does), never blocks
    return Pty(master, slave, os.ttyname(slave))


def damage(data: bytes, faults: Faults, rng: random.Random) -> bytes:
    """Apply drop and corrupt faults to bytes on their way to the client."""
    if faults.drop_rate > 0 and rng.random() < faults.drop_rate:
        cut = rng.randrange(len(data) + 1)
        data = data[:cut]
    if faults.corrupt_rate > 0 and data and rng.random() < faults.corrupt_rate:
        i = rng.randrange(len(data))
        data = data[:i] + bytes([data[i] ^ (1 << rng.randrange(8))]) + data[i + 1 :]
    return data


STALE_PARTIAL_S = 0.5
"""A partial request older than this (s) is dropped when new bytes arrive (Modbus RTU ends a frame
after 3.5 character times of silence; this is generous for a busy computer)."""


def rtu_request_length(buf: bytes) -> int:
    """Length (bytes, CRC included) of the Modbus RTU request ``buf`` starts; 0 while its header
    is incomplete. A function code of no known form takes the whole buffer."""
    if len(buf) < 2:
        return 0
    fc = buf[1]
    if fc in (1, 2, 3, 4, 5, 6, 8):
        return 8  # id, fc, two 16-bit fields, CRC
    if fc in (15, 16):
        return 9 + buf[6] if len(buf) >= 7 else 0  # id, fc, address, quantity, count, data, CRC
    if fc in (7, 11, 12, 17):
        return 4  # id, fc, CRC
    if fc == 43:
        return 7  # id, fc, MEI type, read code, object id, CRC
    return len(buf)


class PtyNullModem:
    """Two ptys cross-connected: ``device_path`` for the server, ``client_path`` for the client.

    The relay runs as reader callbacks on ``loop`` - the asyncio loop the Modbus servers run on -
    so a request, the server's answer and the reply cross no thread boundary inside the
    simulator: a relay thread needed the interpreter lock twice per transaction and, on a busy
    computer, made the simulated device answer hundreds of milliseconds late.

    ``device_id`` (Modbus RTU) makes the modem drop requests addressed to other ids and to
    nobody, so the client sees a silent bus as on real RS-485.
    """

    def __init__(self, faults: Faults, loop: asyncio.AbstractEventLoop, device_id: int | None = None,
                 seed: int = 0) -> None:  # fmt: skip
        self.device_side = open_pty()
        self.client_side = open_pty()
        self.faults = faults
        self.device_id = device_id
        self._loop = loop
        self._rng = random.Random(seed)
        self._closed = False
        self._pending = b""  # the start of a request frame whose rest has not arrived
        self._pending_since = 0.0
        attached = timebase.Event()

        def attach() -> None:
            loop.add_reader(self.client_side.master, self._from_client)
            loop.add_reader(self.device_side.master, self._from_device)
            attached.set()

        loop.call_soon_threadsafe(attach)
        attached.wait(5.0)

    @property
    def device_path(self) -> str:
        """Path the device-side server opens."""
        return self.device_side.path

    @property
    def client_path(self) -> str:
        """Path a client (driver, mbpoll) opens."""
        return self.client_side.path

    def _from_client(self) -> None:
        try:
            data = os.read(self.client_side.master, 4096)
        except OSError:
            return
        if self.faults.disconnect or self.faults.silent:
            self._pending = b""
            return
        if self.device_id is None:
            self._to_device(data)
            return
        # A request can reach this end in pieces (the kernel moves pty data in a worker thread):
        # decide per request frame, not per piece, or the tail of our own station's request is
        # taken for another station's and dropped (the server then waits for it and throws the
        # next request away with it).
        now = self._loop.time()
        if self._pending and now - self._pending_since > STALE_PARTIAL_S:
            self._pending = b""  # a request the client never finished (it died mid-frame)
        if not self._pending:
            self._pending_since = now
        self._pending += data
        while self._pending:
            size = rtu_request_length(self._pending)
            if size == 0 or len(self._pending) < size:
                return  # the rest of the request is still on its way
            frame, self._pending = self._pending[:size], self._pending[size:]
            self._pending_since = now
            if frame[0] == self.device_id:
                self._to_device(frame)
            # else: another station's request, and the bus stays silent

    def _to_device(self, data: bytes) -> None:
        with contextlib.suppress(OSError):
            os.write(self.device_side.master, data)

    def _from_device(self) -> None:
        try:
            data = os.read(self.device_side.master, 4096)
        except OSError:
            return
        if self.faults.disconnect or self.faults.silent:
            return
        out = damage(data, self.faults, self._rng)
        if not out:
            return
        if self.faults.reply_delay_s > 0:
            self._loop.call_later(self.faults.reply_delay_s, self._to_client, out)
        else:
            self._to_client(out)

    def _to_client(self, data: bytes) -> None:
        with contextlib.suppress(OSError):
            os.write(self.client_side.master, data)

    def close(self) -> None:
        """Stop relaying and close the ptys (idempotent)."""
        if self._closed:
            return
        self._closed = True
        detached = timebase.Event()

        def detach() -> None:
            for fd in (self.client_side.master, self.device_side.master):
                with contextlib.suppress(ValueError, OSError):
                    self._loop.remove_reader(fd)
            detached.set()

        if not self._loop.is_closed() and self._loop.is_running():
            self._loop.call_soon_threadsafe(detach)
            detached.wait(2.0)
        self.device_side.close()
        self.client_side.close()


class TcpProxy:
    """A loopback TCP front end for ``backend_port`` with link faults; runs on an asyncio loop."""

    def __init__(self, backend_port: int, faults: Faults, seed: int = 0) -> None:
        self.backend_port = backend_port
        self.faults = faults
        self.port = 0
        self._server: asyncio.Server | None = None
        self._rng = random.Random(seed)
        self._writers: set[asyncio.StreamWriter] = set()

    async def start(self) -> int:
        """Listen on an ephemeral loopback port; returns it."""
        self._server = await asyncio.start_server(self._client, "127.0.0.1", 0)
        self.port = int(self._server.sockets[0].getsockname()[1])
        return self.port

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if self.faults.disconnect:
            writer.close()
            return
        try:
            b_reader, b_writer = await asyncio.open_connection("127.0.0.1", self.backend_port)
        except OSError:
            writer.close()
            return
        self._writers.update((writer, b_writer))

        async def pump(src: asyncio.StreamReader, dst: asyncio.StreamWriter, reply: bool) -> None:
            try:
                while data := await src.read(4096):
                    if self.faults.disconnect:
                        break
                    if reply:
                        if self.faults.silent:
                            continue
                        if self.faults.reply_delay_s > 0:
                            await asyncio.sleep(self.faults.reply_delay_s)
                        data = damage(data, self.faults, self._rng)
                    dst.write(data)
                    await dst.drain()
            except (ConnectionError, OSError):
                pass
            finally:
                dst.close()

        await asyncio.gather(pump(reader, b_writer, False), pump(b_reader, writer, True))
        self._writers.difference_update((writer, b_writer))

    def drop_connections(self) -> None:
        """Close every open connection now (call on the proxy's loop)."""
        for w in list(self._writers):
            w.close()

    async def stop(self) -> None:
        """Stop listening and close connections."""
        self.drop_connections()
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
