"""Honeywell HMR2300 on a serial line: the datasheet command set, ASCII and binary output.

Commands are ``*ddCMD<CR>`` (``dd`` the two-digit ID, 99 = everyone); write-protected commands need
``*ddWE`` immediately before, on its own line (answered ``OK``) or on the command's line as the
datasheet's command table writes it, ``*ddWE *ddA<CR>`` (only the command answers: ``ASCII ON``).
The serial number and software version replies are as long as the table gives them: ``SER# ``
and ``S/W vers: `` followed by a 16-character field (22 and 27 bytes with the CR; the field's
padding, spaces after the value, is not in the table; ``H/W vers:`` is taken to be alike). Output: 15000 counts per gauss (150 per uT), +-30000 counts; binary
frames are ``XH XL YH YL ZH ZL CR`` (two's complement, big-endian); ASCII samples are 28 bytes.
The line is paced at 10 bits per byte at the configured baud rate, so the achievable sample rate
is what the datasheet table gives (binary: 154 sps at 19200 baud; ASCII: 50 sps).

The line is a pseudo-terminal, or in simulated time a line of the simulated clock
(:mod:`sim.serial_line`). ``half_duplex`` models the RS-485 variant (HMR2300-D21-485): one pair
carries both ways, so a byte the host sends while the sensor is transmitting collides with it and
is lost to the sensor (an ESC sent while a streamed frame is on the line does not stop the
stream); the sensor's own frame is not damaged here.

Timing model: the device keeps its own sample clock (slot ``k`` is due at ``t0 + k / rate``, s,
``timebase.monotonic``) and its own UART timeline (each byte occupies the line for ``10 / baud`` s).
Both are computed, not slept: the device thread never waits for the line, and when it wakes late
(our process was descheduled, or another thread held the interpreter lock) it sends every frame
that fell due meanwhile back to back, as the UART would already have delivered them. So the sample
clock never slips, and nothing leaves faster than the line carries (at most 274 binary frames/s at
19200 baud). A sample that falls due while the transmitter already holds a frame waiting behind the
one on the wire is not output (``samples_skipped``): a rate above the line's capacity gives the
line's capacity.
"""

from __future__ import annotations

import random
import struct
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

import timebase
from sim.device_kind import CageHost, SimKind
from sim.perming import Perming
from sim.physics import Faults
from sim.serial_line import open_line
from sim.transports import damage

if TYPE_CHECKING:
    from sim.config import MagnetometerConfig

COUNTS_PER_UT = 150.0
FULL_SCALE_COUNTS = 30000
RATES_SPS = (10, 20, 25, 30, 40, 50, 60, 100, 123, 154)
ESC = 0x1B
ID_FIELD_CHARS = 16
"""The width of the serial number and version fields: ``*dd#`` answers 22 bytes, ``*ddF`` 27."""


def counts_from_ut(field_ut: np.ndarray) -> tuple[int, int, int]:
    """Quantize and saturate a reading (uT) to HMR2300 counts."""
    c = np.clip(
        np.round(np.asarray(field_ut) * COUNTS_PER_UT), -FULL_SCALE_COUNTS, FULL_SCALE_COUNTS
    )
    return int(c[0]), int(c[1]), int(c[2])


def binary_frame(counts: tuple[int, int, int]) -> bytes:
    """7-byte binary sample."""
    return struct.pack(">hhh", *counts) + b"\r"


def ascii_frame(counts: tuple[int, int, int]) -> bytes:
    """28-byte ASCII sample: per axis sign, 2 digits, comma, 3 digits, 2 spaces; then CR."""
    parts = []
    for c in counts:
        sign = "-" if c < 0 else " "
        thousands, units = divmod(abs(c), 1000)
        parts.append(f"{sign}{thousands:2d},{units:03d}  ")
    return ("".join(parts) + "\r").encode("ascii")


class Hmr2300:
    """The device. ``read_ut(t_s)`` returns the sensor's field (uT) at device time ``t_s``
    (monotonic s): each streamed sample is taken at its slot time, so frames sent back to back
    after our thread was late carry the field of their own slots, as a real sensor's would, not
    the field at the moment the thread ran."""

    def __init__(self, read_ut: Callable[[float], np.ndarray], faults: Faults, *, device_id: int = 0,
                 baudrate: int = 9600, serial_number: str = "0123", seed: int = 0,
                 perming: Perming | None = None, name: str = "hmr2300",
                 half_duplex: bool = False) -> None:  # fmt: skip
        self.read_ut = read_ut
        self.faults = faults
        self.perming = perming or Perming(0.0, 0.0)
        """The sensor's perming: cleared by set/reset pulses (``]S``/``]R``, and S/R mode)."""
        self.device_id = device_id
        self.baudrate = baudrate
        self.serial_number = serial_number
        self.binary = False
        self.rate_sps = 20
        self.set_reset = True
        self.perming.set_auto_reset(True)
        self.zero_offset = np.zeros(3)
        self.zero_on = False
        self.average = False
        self.reenter_reply = True
        self.streaming = False
        self.write_enabled = False
        self._avg: np.ndarray | None = None
        self._invalid_after_pulse = 0
        self.samples_sent = 0  # every sample output, polled and streamed (silent/disconnect: lost)
        self.samples_skipped = 0  # stream slots not output because the transmitter was full
        self.bytes_overrun = 0  # bytes the client's side refused (its buffer was full): lost
        self.half_duplex = half_duplex
        self.bytes_collided = 0  # the host's bytes lost to collisions (half duplex)
        self._sending: deque[tuple[float, float]] = deque()  # (start, end) s of recent frames
        # (samples_sent, device time s of that sample's slot), replaced as one tuple per streamed
        # sample so that another thread reads a consistent pair.
        self.stream_clock: tuple[int, float] = (0, 0.0)
        self.line = open_line(name, baudrate)
        self._rng = random.Random(seed)
        self._stop = timebase.Event()
        self._line_free_at = 0.0  # device time s when the UART has sent everything queued
        self._out: deque[tuple[float, bytes]] = deque()  # (time due to the line s, bytes), in order
        self._last_start = 0.0  # device time s when the last queued bytes start on the line
        self._clock_t0 = 0.0  # device time s of slot 0 of the stream
        self._slot = 0  # next stream slot
        self._thread = timebase.Thread(self._run, name=name, daemon=True)
        self._thread.start()

    @property
    def path(self) -> str:
        """The serial port path a client opens (a pty, or ``simpipe://<name>``)."""
        return self.line.path

    @property
    def stream_start_s(self) -> float:
        """Device time (s, ``timebase.monotonic``) of slot 0 of the current or last stream."""
        return self._clock_t0

    def _client_baud_matches(self) -> bool:
        """The speed the client set (a pty's termios, a simulated line's setting): a client at
        the wrong speed would only see garbage on a real line, so the device ignores it."""
        baud = self.line.client_baud()
        return baud is None or baud == self.baudrate

    # --- output ---------------------------------------------------------------------------------

    def _send(self, data: bytes, at_s: float | None = None) -> None:
        """Queue bytes for the UART: they start when the line is free, not before ``at_s`` (device
        time s, default now), and occupy it for 10 bits per byte."""
        if self.faults.silent or self.faults.disconnect:
            return
        data = damage(data, self.faults, self._rng)
        start = max(timebase.monotonic() if at_s is None else at_s, self._line_free_at)
        self._line_free_at = start + len(data) * 10.0 / self.baudrate
        if self.half_duplex:
            while self._sending and self._sending[0][1] < start - 1.0:
                self._sending.popleft()  # long over: no host byte can still overlap it
            self._sending.append((start, self._line_free_at))
        self._last_start = start
        # handed to the line when its last byte has left (or at its start where the line itself
        # carries the line time, a simulated line)
        self._out.append((start if self.line.carries_line_time else self._line_free_at, data))

    def _flush(self, now: float) -> None:
        """Hand the line every queued frame due by ``now`` (s): its transmission started (a line
        that carries the line time) or ended (a pty)."""
        while self._out and self._out[0][0] <= now:
            _, data = self._out.popleft()
            try:
                written = self.line.write(data)
            except OSError:
                self._out.clear()
                return
            self.bytes_overrun += len(data) - written

    def _reply(self, text: str) -> None:
        self._send(text.encode("ascii") + b"\r")

    def _sample(self, at_s: float | None = None) -> bytes:
        """One output frame of the field at device time ``at_s`` (s; default now)."""
        reading = np.asarray(
            self.read_ut(timebase.monotonic() if at_s is None else at_s), dtype=float
        )
        if self.average:
            self._avg = reading if self._avg is None else 0.5 * reading + 0.5 * self._avg
            reading = self._avg
        if self.zero_on:
            reading = reading - self.zero_offset
        if self._invalid_after_pulse > 0:
            self._invalid_after_pulse -= 1
            reading = reading + 5.0 * np.sign(reading + 1e-9)  # the datasheet: readings invalid
        counts = counts_from_ut(reading)
        self.samples_sent += 1
        return binary_frame(counts) if self.binary else ascii_frame(counts)

    # --- commands -------------------------------------------------------------------------------

    def handle(self, line: str) -> None:
        """Execute one command line (without the CR): a command, or write enable and the command
        it covers on one line (``*ddWE *ddCMD``: only the command answers)."""
        if not line.startswith("*"):
            return
        first, star, rest = line[1:].partition("*")
        if star and first.strip().upper()[2:] == "WE" and "*" not in rest:
            self._execute(first.strip(), quiet=True)
            self._execute(rest.strip())
        else:
            self._execute(line[1:])

    def _execute(self, body: str, quiet: bool = False) -> None:
        """One command ``ddCMD`` (``quiet``: a write enable that does not answer)."""
        if len(body) >= 10 or len(body) < 2 or not body[:2].isdigit():
            self._reenter()
            return
        dd = int(body[:2])
        if dd not in (self.device_id, 99):
            return
        cmd = body[2:].upper()
        if cmd == "WE" and quiet:
            self.write_enabled = True
            return
        we, self.write_enabled = self.write_enabled, False
        protected = {
            "A", "B", "TN", "TF", "T", "ZN", "ZF", "ZR", "VN", "VF", "V", "Y", "N", "D", "RST", "SP",
        }  # fmt: skip
        if cmd == "WE":
            self.write_enabled = True
            self._reply("OK")
        elif cmd in protected or (cmd.startswith(("R=", "ID=", "!BR=")) and cmd != "ID="):
            if not we:
                self._reply("WE OFF")
                return
            self._protected(cmd)
        elif cmd == "P":
            self._send(self._sample())
        elif cmd == "C":
            if not self.streaming:
                self.streaming = True
                self._restart_clock()
        elif cmd == "ID=":
            self._reply(f"ID= {self.device_id:02d}")
        elif cmd in ("]S", "]R", "]"):
            self.perming.reset()
            self._invalid_after_pulse = 3
            self._reply({"]S": "SET", "]R": "RST", "]": "SET"}[cmd])
        elif cmd == "#":
            self._reply(f"SER# {self.serial_number:<{ID_FIELD_CHARS}}")
        elif cmd == "F":
            self._reply(f"S/W vers: {'3.12':<{ID_FIELD_CHARS}}")
        elif cmd == "H":
            self._reply(f"H/W vers: {'2.01':<{ID_FIELD_CHARS}}")
        elif cmd == "Q":
            fmt = "BINARY ON" if self.binary else "ASCII ON"
            self._reply(
                f"{fmt}, {'CONT' if self.streaming else 'POLLED'}, S/R {'ON' if self.set_reset else 'OFF'},"
                f" ZERO {'ON' if self.zero_on else 'OFF'}, AVG {'ON' if self.average else 'OFF'},"
                f" R {'ON' if self.reenter_reply else 'OFF'}, ID= {self.device_id:02d}, {self.rate_sps} sps"
            )
        else:
            self._reenter()

    def _reenter(self) -> None:
        if self.reenter_reply:
            self._reply("Re-enter")

    def _protected(self, cmd: str) -> None:
        if cmd == "A":
            self.binary = False
            self._reply("ASCII ON")
        elif cmd == "B":
            self.binary = True
            self._reply("BINARY ON")
        elif cmd.startswith("R="):
            try:
                rate = int(cmd[2:])
            except ValueError:
                rate = -1
            if rate not in RATES_SPS:
                self._reenter()
                return
            self.rate_sps = rate
            self._restart_clock()
            self._reply("OK")
        elif cmd.startswith("ID="):
            try:
                new_id = int(cmd[3:])
            except ValueError:
                new_id = -1
            if not 0 <= new_id <= 98:
                self._reenter()
                return
            self.device_id = new_id
            self._reply("OK")
        elif cmd.startswith("!BR="):
            baud = {"S": 9600, "F": 19200}.get(cmd[4:])
            if baud is None:
                self._reenter()
                return
            self._reply("OK")
            self._reply("BAUD= 9600" if baud == 9600 else "BAUD= 19,200")
            self.baudrate = baud  # the client must now reopen the port at the new speed
            self.line.set_baud(baud)
        elif cmd in ("TN", "TF", "T", "ZN", "ZF", "ZR", "VN", "VF", "V"):
            self._mode(cmd)
        elif cmd in ("Y", "N"):
            self.reenter_reply = cmd == "Y"
            self._reply("OK")
        elif cmd in ("D", "RST"):
            self.binary, self.rate_sps, self.set_reset = False, 20, True
            self.perming.set_auto_reset(True)
            self._restart_clock()
            self.zero_on = self.average = False
            self.reenter_reply = True
            self._reply("OK")
            self._reply("BAUD= 9600" if self.baudrate == 9600 else "BAUD= 19,200")
        elif cmd == "SP":
            self._reply("OK")

    def _mode(self, cmd: str) -> None:
        """The on/off/toggle modes: set/reset (T), zero (Z), averaging (V)."""
        if cmd[0] == "T":
            self.set_reset = {"TN": True, "TF": False, "T": not self.set_reset}[cmd]
            self.perming.set_auto_reset(self.set_reset)
            self._reply("S/R ON" if self.set_reset else "S/R OFF")
        elif cmd[0] == "Z":
            self.zero_on = {"ZN": True, "ZF": False, "ZR": not self.zero_on}[cmd]
            if self.zero_on:
                self.zero_offset = np.asarray(self.read_ut(timebase.monotonic()), dtype=float)
            self._reply("ZERO ON" if self.zero_on else "ZERO OFF")
        else:
            self.average = {"VN": True, "VF": False, "V": not self.average}[cmd]
            self._avg = None
            self._reply("AVG ON" if self.average else "AVG OFF")

    # --- loop -----------------------------------------------------------------------------------

    def _restart_clock(self) -> None:
        """The sample clock starts now: slot 0 is due immediately."""
        self._clock_t0 = timebase.monotonic()
        self._slot = 0

    def _slot_due(self) -> float:
        """Device time (s) of the next stream slot."""
        return self._clock_t0 + self._slot / self.rate_sps

    def _emit_due(self, now: float) -> None:
        """Output the sample of every stream slot due by ``now`` (s), each at its slot time."""
        while self.streaming and (due := self._slot_due()) <= now:
            self._slot += 1
            if self._last_start > due:
                self.samples_skipped += 1  # a frame is already waiting behind the one on the wire
                continue
            self._send(self._sample(due), at_s=due)
            self.stream_clock = (self.samples_sent, due)

    def _run(self) -> None:
        buf = bytearray()
        while not self._stop.is_set():
            now = timebase.monotonic()
            wake = now + 0.05
            if self.streaming:
                wake = min(wake, self._slot_due())
            if self._out:
                wake = min(wake, self._out[0][0])
            try:
                ready = self.line.wait_readable(max(0.0, wake - now))
            except (OSError, ValueError):
                return
            self._emit_due(timebase.monotonic())  # they fell due before we looked at the input
            if ready:
                data = self.line.read_available()
                if self.faults.disconnect or not self._client_baud_matches():
                    data = b""
                self._take(data, buf)
                self._emit_due(timebase.monotonic())
            self._flush(timebase.monotonic())

    def _heard(self, data: bytes) -> bytes:
        """The host's bytes that reached the sensor: on a half-duplex line those that were on
        it while the sensor transmitted are lost (``data`` has just arrived: its last byte
        ended now, each took 10 bits at the baud rate)."""
        if not self.half_duplex or not data:
            return data
        now, byte_s = timebase.monotonic(), 10.0 / self.baudrate
        first = now - len(data) * byte_s
        while self._sending and self._sending[0][1] <= first:
            self._sending.popleft()  # over before these bytes began
        kept = bytearray()
        for i, byte in enumerate(data):
            start, end = first + i * byte_s, first + (i + 1) * byte_s
            if any(s < end and start < e for s, e in self._sending):
                self.bytes_collided += 1
            else:
                kept.append(byte)
        return bytes(kept)

    def _take(self, data: bytes, buf: bytearray) -> None:
        """Act on the client's bytes: ESC stops a stream, CR ends a command (kept in ``buf``)."""
        for byte in self._heard(data):
            if byte == ESC:
                self.streaming = False
                buf.clear()
            elif byte == 0x0D:
                line = buf.decode("ascii", errors="replace").strip()
                buf.clear()
                self.handle(line)
            elif byte != 0x0A:
                buf.append(byte)

    def close(self) -> None:
        """Stop the device thread and close the line."""
        self._stop.set()
        self._thread.join(timeout=10.0)  # it must not touch the line once it is closed
        self.line.close()


def _start(host: CageHost, m: MagnetometerConfig, index: int) -> dict[str, Any]:
    """An HMR2300 on a serial line at the DUT position."""
    dev = Hmr2300(host.field_reader(m.name), host.physics.magnetometers[m.name].faults,
                  device_id=m.endpoint.device_id, baudrate=m.endpoint.baudrate,
                  serial_number=m.serial_number, seed=host.cfg.seed + index,
                  perming=host.physics.magnetometers[m.name].perming, name=m.name)  # fmt: skip
    host.add_serial(m.name, dev)
    return {"kind": "hmr2300", "protocol": "serial", "path": dev.path,
            "baudrate": m.endpoint.baudrate, "device_id": m.endpoint.device_id}  # fmt: skip


KIND = SimKind("hmr2300", "magnetometers", _start)
