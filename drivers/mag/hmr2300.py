"""Honeywell HMR2300 smart magnetometer (RS-232/RS-485) by its datasheet command set.

* Commands ``*ddCMD<CR>``; write-protected ones are preceded by ``*ddWE``.
* 15000 counts per gauss = 150 counts per uT, +-30000 counts.
* Binary samples are 7 bytes ``XH XL YH YL ZH ZL CR`` (two's complement, big-endian). A data byte
  can be 0x0D, so frames are read by fixed length and realigned on the stride of 7, never split on CR.
* ASCII samples are 28 bytes: per axis sign, two digits, comma, three digits, two spaces; then CR.
* ESC stops a stream. The driver goes on only once the line has been silent for longer than the
  gap between two frames (bytes still on their way would be read as the next command's reply),
  and sends ESC again while frames keep coming: on the half-duplex RS-485 variant an ESC sent
  while a frame is on the pair collides with it and is lost.
"""

from __future__ import annotations

import struct
from collections.abc import Callable, Iterator
from typing import TypeVar

import timebase
from drivers.errors import (
    DeviceError,
    DeviceNotFoundError,
    DeviceProtocolError,
    DeviceRefusedError,
    DeviceTimeoutError,
)
from drivers.identity import Identity
from drivers.transport.serial_port import SerialPort

T = TypeVar("T")
COUNTS_PER_UT = 150.0
RATES_SPS = (10, 20, 25, 30, 40, 50, 60, 100, 123, 154)
BINARY_LEN, ASCII_LEN = 7, 28
ESC = b"\x1b"
STOP_ESC_ATTEMPTS = 4
"""ESCs sent to stop a stream before the driver gives up on the line falling silent."""
SENSOR_LATENCY_S = 0.01
"""Margin for the sensor's own delay in the silence that shows a stream has stopped (s): the
datasheet gives about 2 ms from a command's CR to its reply."""
DAMAGED_RETRIES = 10
"""A command whose reply came back damaged or cut short is asked again up to this many times (the
sensor answers; the line is noisy): at 28 % of replies damaged, a WE + command pair then fails
about once in 3000 where three tries failed once in nine."""


def parse_binary(frame: bytes) -> tuple[float, float, float]:
    """One 7-byte binary frame to uT."""
    if len(frame) != BINARY_LEN or frame[6] != 0x0D:
        raise DeviceProtocolError(f"HMR2300: bad binary frame {frame!r}")
    x, y, z = struct.unpack(">hhh", frame[:6])
    return x / COUNTS_PER_UT, y / COUNTS_PER_UT, z / COUNTS_PER_UT


def parse_ascii(frame: bytes) -> tuple[float, float, float]:
    """One 28-byte ASCII sample to uT (accepts blank, '+' or '-' signs and blanked zeros)."""
    if len(frame) != ASCII_LEN or not frame.endswith(b"\r"):
        raise DeviceProtocolError(f"HMR2300: bad ASCII sample {frame!r}")
    text = frame.decode("ascii", errors="replace")
    out = []
    for start in (0, 9, 18):
        field = text[start : start + 7].replace(",", "").replace(" ", "")
        try:
            out.append(int(field) / COUNTS_PER_UT)
        except ValueError:
            raise DeviceProtocolError(
                f"HMR2300: unreadable axis value {text[start : start + 7]!r}"
            ) from None
    return out[0], out[1], out[2]


class Hmr2300:
    """An HMR2300 on a serial port (path or pyserial URL).

    Opening it stops a stream left running (ESC, then a silence as long as the gap between two
    frames at the slowest rate: :meth:`stop_stream`), finds its ID and turns its automatic set/reset
    on (``*ddWE``, ``*ddTN``): a perming step turns it off for its holds and a step killed there
    left it off (issue 51), so every session starts from the sensor's default. ``set_reset_auto``
    False leaves the mode as found (a bring-up scan that only looks)."""

    def __init__(self, url: str, *, baudrate: int = 9600, device_id: int | None = None,
                 timeout_s: float = 0.5, retries: int = 2, name: str = "HMR2300",
                 set_reset_auto: bool = True) -> None:  # fmt: skip
        self.name = name
        self.port = SerialPort(url, baudrate, timeout_s=timeout_s, name=name)
        self.retries = retries
        self.binary = False
        self.rate_sps: int | None = None
        """The stream rate this session set (None: not known, a stream left running by another
        session is taken to be at the slowest rate)."""
        self.streaming = False
        self._buf = bytearray()
        self.resyncs = 0
        self.samples_lost = 0
        """Streamed samples lost to damaged or cut-short frames (counted by the bytes skipped)."""
        self.lost_before: tuple[int, ...] = ()
        """Per sample of the last :meth:`read_stream`: samples lost just before it (empty: none)."""
        self._skipped = 0  # bytes skipped since the last whole frame
        self.stop_stream()  # a stream left running by a previous session
        self.device_id = self._query_id() if device_id is None else device_id
        if set_reset_auto:
            self.set_reset_auto(True)

    # --- commands -------------------------------------------------------------------------------

    def _command(self, cmd: str, expect: str | None = None, device_id: int | None = None,
                 retry: bool = True, prefix: str | None = None) -> str:  # fmt: skip
        """Send ``*ddcmd`` and return the reply line (without CR); a missing or damaged reply
        (not ``expect``, or not starting with ``prefix``) is asked again
        (:meth:`_asking_again`) unless ``retry`` is False."""
        dd = self.device_id if device_id is None else device_id
        line = f"*{dd:02d}{cmd}\r".encode("ascii")

        def once() -> str:
            self.port.write(line)
            reply = self.port.read_until(b"\r").decode("ascii", errors="replace").rstrip("\r")
            if reply == "WE OFF":
                raise DeviceRefusedError(
                    f"{self.name} on {self.port.url}: '{cmd}' needs write enable (WE)"
                )
            if reply == "Re-enter":
                raise DeviceRefusedError(
                    f"{self.name} on {self.port.url}: '{cmd}' was not understood (Re-enter)"
                )
            wanted = expect if expect is not None else prefix
            if (expect is not None and reply != expect) or not reply.startswith(prefix or ""):
                raise DeviceProtocolError(
                    f"{self.name} on {self.port.url}: '{cmd}' answered {reply!r}, expected {wanted!r}"
                )
            return reply

        return self._asking_again(once) if retry else once()

    def _protected(self, cmd: str, expect: str) -> str:
        """``WE`` then ``cmd``, the pair asked again when either reply is missing or damaged: the
        sensor's write enable holds for one command, so a command asked again needs its own."""
        return self._asking_again(
            lambda: (
                self._command("WE", "OK", retry=False),
                self._command(cmd, expect, retry=False),
            )[1]
        )

    def _asking_again(self, exchange: Callable[[], T]) -> T:
        """``exchange()`` until it answers: asked again after silence or a refusal up to the
        driver's ``retries`` times, after a damaged or cut-short reply (a sensor that answers, on
        a noisy line) up to :data:`DAMAGED_RETRIES` times; the last error then."""
        silent = damaged = 0
        while True:
            try:
                return exchange()
            except DeviceTimeoutError as exc:
                last: DeviceError = exc
                if exc.partial:
                    damaged += 1
                else:
                    silent += 1
            except DeviceProtocolError as exc:
                last = exc
                damaged += 1
            except DeviceRefusedError as exc:
                last = exc
                silent += 1
            if silent > self.retries or damaged > DAMAGED_RETRIES:
                raise last
            self.port.drain_input()

    def _query_id(self) -> int:
        reply = self._command("ID=", device_id=99)
        if not reply.startswith("ID="):
            raise DeviceNotFoundError(
                f"{self.name} on {self.port.url}: answered {reply!r} to *99ID=; is it an HMR2300?"
            )
        return int(reply[3:].strip())

    def identify(self) -> Identity:
        """Serial number (``*dd#``) and software version (``*ddF``); the ID is ``device_id``."""
        serial = self._command("#", prefix="SER#")
        firmware = self._command("F", prefix="S/W")
        return Identity("HMR2300", serial[4:].strip(), firmware.split(":")[-1].strip())

    def set_binary(self, binary: bool) -> None:
        """Binary (7-byte) or ASCII (28-byte) output."""
        self._protected("B" if binary else "A", "BINARY ON" if binary else "ASCII ON")
        self.binary = binary

    def set_rate(self, sps: int) -> None:
        """Continuous-mode sample rate, one of the datasheet's rates."""
        if sps not in RATES_SPS:
            raise ValueError(f"{self.name}: {sps} sps is not one of {RATES_SPS}")
        self._protected(f"R={sps}", "OK")
        self.rate_sps = sps

    def set_reset_auto(self, on: bool) -> None:
        """Automatic set/reset pulses (S/R mode: on by default, clearing perming as the sensor
        reads); off, a strong field's perming stays until :meth:`set_reset_pulse`."""
        self._protected("TN" if on else "TF", "S/R ON" if on else "S/R OFF")

    def set_reset_pulse(self) -> None:
        """One set/reset pulse (degaussing); the next three readings are discarded here."""
        self._command("]S", "SET")
        for _ in range(3):
            self.read()

    # --- sampling (the Magnetometer protocol) ---------------------------------------------------

    self_timed = True
    """Streams at its own clock once :meth:`start_sampling` has run."""

    def start_sampling(self, rate_hz: float) -> float:
        """Binary stream at the lowest datasheet rate at or above ``rate_hz`` (154 sps at most):
        binary because ASCII cannot carry more than 50 sps at 19200 baud. Returns the rate (sps)."""
        self.set_binary(True)
        rate = min((r for r in RATES_SPS if r >= rate_hz), default=RATES_SPS[-1])
        self.set_rate(rate)
        self.start_stream()
        return float(rate)

    def read_samples(self, max_wait_s: float) -> list[tuple[float, float, float]]:
        """The streamed samples received so far (uT, oldest first)."""
        return self.read_stream(max_wait_s)

    def stop_sampling(self) -> None:
        """Stop the stream (ESC)."""
        if self.streaming:
            self.stop_stream()

    # --- data -----------------------------------------------------------------------------------

    def read(self) -> tuple[float, float, float]:
        """One polled sample (uT); a damaged or cut-short frame, or none, is asked again as a
        command's reply is (:meth:`_asking_again`)."""
        if self.streaming:
            raise RuntimeError("stop the stream before polling")
        n = BINARY_LEN if self.binary else ASCII_LEN

        def once() -> tuple[float, float, float]:
            self.port.write(f"*{self.device_id:02d}P\r".encode("ascii"))
            frame = self.port.read_exact(n)
            return parse_binary(frame) if self.binary else parse_ascii(frame)

        return self._asking_again(once)

    def start_stream(self) -> None:
        """Continuous output at the set rate."""
        self._buf.clear()
        self._skipped = 0
        self.port.write(f"*{self.device_id:02d}C\r".encode("ascii"))
        self.streaming = True

    def stop_stream(self) -> None:
        """ESC stops the stream. Returns once the line has been silent for longer than the gap
        between two frames (:meth:`_stopped_quiet_s`), what came meanwhile discarded; ESC is
        sent again while frames keep coming (an ESC lost in a collision on RS-485)."""
        self.streaming = False
        self._buf.clear()
        self._skipped = 0
        quiet_s = self._stopped_quiet_s()
        for _ in range(STOP_ESC_ATTEMPTS):
            self.port.write(ESC)
            if self.port.wait_silent(quiet_s, 2.0 * quiet_s):
                return
        raise DeviceProtocolError(
            f"{self.name} on {self.port.url}: the line did not fall silent after"
            f" {STOP_ESC_ATTEMPTS} ESC (a stream that does not stop, or another device talking);"
            " check the baud rate and the cable, and on RS-485 that nothing else talks on the pair"
        )

    def _stopped_quiet_s(self) -> float:
        """How long the line must stay silent to show that a stream has stopped (s): the gap
        between two frames at the rate this session set (the slowest when unknown), two frames'
        line time (a frame in flight) and :data:`SENSOR_LATENCY_S`."""
        frame_s = (BINARY_LEN if self.binary else ASCII_LEN) * 10.0 / self.port.baudrate
        return 1.0 / (self.rate_sps or RATES_SPS[0]) + 2.0 * frame_s + SENSOR_LATENCY_S

    def _frames(self, data: bytes) -> Iterator[tuple[int, tuple[float, float, float]]]:
        """(samples lost just before it, sample) for each frame in the stream buffer,
        realigning on the stride when a frame is broken: the bytes skipped to realign are
        ``ceil(skipped / frame length)`` lost samples (a damaged frame, or a cut-short one)."""
        self._buf += data
        n = BINARY_LEN if self.binary else ASCII_LEN
        while len(self._buf) >= n:
            frame = bytes(self._buf[:n])
            if frame[-1] == 0x0D and (self.binary or frame[3:4] == b","):
                try:
                    value = parse_binary(frame) if self.binary else parse_ascii(frame)
                except DeviceProtocolError:
                    value = None
                if value is not None:
                    del self._buf[:n]
                    lost, self._skipped = -(-self._skipped // n), 0
                    yield lost, value
                    continue
            # Misaligned or damaged: drop one byte and look for a frame whose last byte is CR and
            # whose next frame boundary also holds a CR (binary data may contain 0x0D).
            self.resyncs += 1
            before = len(self._buf)
            del self._buf[:1]
            while len(self._buf) >= 2 * n and not (
                self._buf[n - 1] == 0x0D and self._buf[2 * n - 1] == 0x0D
            ):
                del self._buf[:1]
            self._skipped += before - len(self._buf)

    @property
    def frame_line_s(self) -> float:
        """How long one sample's frame takes on the line (s): 10 bits a byte at the port's speed.
        A streamed sample arrives this long after the sensor sent it (the sampler dates it so)."""
        return (BINARY_LEN if self.binary else ASCII_LEN) * 10.0 / self.port.baudrate

    def read_stream(self, max_wait_s: float = 0.5) -> list[tuple[float, float, float]]:
        """All complete samples received so far (waits up to ``max_wait_s`` for at least one);
        :attr:`lost_before` says which samples the stream lost before each."""
        deadline = timebase.monotonic() + max_wait_s
        out = list(self._frames(self.port.read_available()))
        while not out:
            left = deadline - timebase.monotonic()
            if left <= 0 or not self.port.wait_readable(left):  # waits on the port, not a poll
                break
            out = list(self._frames(self.port.read_available()))
        lost = tuple(k for k, _ in out)
        self.lost_before = lost if any(lost) else ()
        self.samples_lost += sum(lost)
        return [xyz for _, xyz in out]

    def close(self) -> None:
        """Stop any stream and close the port."""
        try:
            if self.streaming:
                self.stop_stream()
        finally:
            self.port.close()
