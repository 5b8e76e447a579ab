"""Honeywell HMR2300 on a pseudo-terminal: the datasheet command set, ASCII and binary output.

Commands are ``*ddCMD<CR>`` (``dd`` the two-digit ID, 99 = everyone); write-protected commands need
``*ddWE`` immediately before. Output: 15000 counts per gauss (150 per uT), +-30000 counts; binary
frames are ``XH XL YH YL ZH ZL CR`` (two's complement, big-endian); ASCII samples are 28 bytes.
The line is paced at 10 bits per byte at the configured baud rate, so the achievable sample rate
is what the datasheet table gives (binary: 154 sps at 19200 baud; ASCII: 50 sps).
"""

from __future__ import annotations

import os
import random
import select
import struct
import termios
import threading
import time
from collections.abc import Callable

import numpy as np

from sim.links import damage, open_pty
from sim.physics import Faults

COUNTS_PER_UT = 150.0
FULL_SCALE_COUNTS = 30000
RATES_SPS = (10, 20, 25, 30, 40, 50, 60, 100, 123, 154)
ESC = 0x1B
BAUD_CONSTANTS = {9600: termios.B9600, 19200: termios.B19200}


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
    """The device. ``read_ut`` returns the sensor's field (uT) at the moment of sampling."""

    def __init__(self, read_ut: Callable[[], np.ndarray], faults: Faults, *, device_id: int = 0,
                 baudrate: int = 9600, serial_number: str = "0123", seed: int = 0) -> None:  # fmt: skip
        self.read_ut = read_ut
        self.faults = faults
        self.device_id = device_id
        self.baudrate = baudrate
        self.serial_number = serial_number
        self.binary = False
        self.rate_sps = 20
        self.set_reset = True
        self.zero_offset = np.zeros(3)
        self.zero_on = False
        self.average = False
        self.reenter_reply = True
        self.streaming = False
        self.write_enabled = False
        self._avg: np.ndarray | None = None
        self._invalid_after_pulse = 0
        self.samples_sent = 0
        self.pty = open_pty()
        self._set_line_speed(baudrate)
        self._rng = random.Random(seed)
        self._stop = threading.Event()
        self._line_free_at = 0.0
        self._thread = threading.Thread(target=self._run, name="hmr2300", daemon=True)
        self._thread.start()

    @property
    def path(self) -> str:
        """The serial port path a client opens."""
        return self.pty.path

    def _set_line_speed(self, baud: int) -> None:
        attrs = termios.tcgetattr(self.pty.master)
        attrs[4] = attrs[5] = BAUD_CONSTANTS[baud]
        termios.tcsetattr(self.pty.master, termios.TCSANOW, attrs)

    def _client_baud_matches(self) -> bool:
        """A pty carries no baud rate, but the client's termios speed is visible: a client at the
        wrong speed would only see garbage on a real line, so the device ignores it."""
        try:
            speed = termios.tcgetattr(self.pty.slave)[5]
        except termios.error:
            return True
        return bool(speed == BAUD_CONSTANTS[self.baudrate])

    # --- output ---------------------------------------------------------------------------------

    def _send(self, data: bytes) -> None:
        """Write at the line rate: 10 bits per byte."""
        if self.faults.silent or self.faults.disconnect:
            return
        data = damage(data, self.faults, self._rng)
        now = time.monotonic()
        start = max(now, self._line_free_at)
        self._line_free_at = start + len(data) * 10.0 / self.baudrate
        try:
            os.write(self.pty.master, data)
        except OSError:
            return
        delay = self._line_free_at - time.monotonic()
        if delay > 0:
            self._stop.wait(delay)

    def _reply(self, text: str) -> None:
        self._send(text.encode("ascii") + b"\r")

    def _sample(self) -> bytes:
        reading = np.asarray(self.read_ut(), dtype=float)
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
        """Execute one command line (without the CR)."""
        if not line.startswith("*"):
            return
        body = line[1:]
        if len(body) >= 10 or len(body) < 2 or not body[:2].isdigit():
            self._reenter()
            return
        dd = int(body[:2])
        if dd not in (self.device_id, 99):
            return
        cmd = body[2:].upper()
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
            self.streaming = True
        elif cmd == "ID=":
            self._reply(f"ID= {self.device_id:02d}")
        elif cmd in ("]S", "]R", "]"):
            self._invalid_after_pulse = 3
            self._reply({"]S": "SET", "]R": "RST", "]": "SET"}[cmd])
        elif cmd == "#":
            self._reply(f"SER# {self.serial_number}")
        elif cmd == "F":
            self._reply("S/W vers: 3.12")
        elif cmd == "H":
            self._reply("H/W vers: 2.01")
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
        elif cmd in ("TN", "TF", "T"):
            self.set_reset = {"TN": True, "TF": False, "T": not self.set_reset}[cmd]
            self._reply("S/R ON" if self.set_reset else "S/R OFF")
        elif cmd in ("ZN", "ZF", "ZR"):
            self.zero_on = {"ZN": True, "ZF": False, "ZR": not self.zero_on}[cmd]
            if self.zero_on:
                self.zero_offset = np.asarray(self.read_ut(), dtype=float)
            self._reply("ZERO ON" if self.zero_on else "ZERO OFF")
        elif cmd in ("VN", "VF", "V"):
            self.average = {"VN": True, "VF": False, "V": not self.average}[cmd]
            self._avg = None
            self._reply("AVG ON" if self.average else "AVG OFF")
        elif cmd in ("Y", "N"):
            self.reenter_reply = cmd == "Y"
            self._reply("OK")
        elif cmd in ("D", "RST"):
            self.binary, self.rate_sps, self.set_reset = False, 20, True
            self.zero_on = self.average = False
            self.reenter_reply = True
            self._reply("OK")
            self._reply("BAUD= 9600" if self.baudrate == 9600 else "BAUD= 19,200")
        elif cmd == "SP":
            self._reply("OK")

    # --- loop -----------------------------------------------------------------------------------

    def _run(self) -> None:
        buf = bytearray()
        next_sample = time.monotonic()
        while not self._stop.is_set():
            timeout = max(0.0, next_sample - time.monotonic()) if self.streaming else 0.05
            try:
                ready, _, _ = select.select([self.pty.master], [], [], timeout)
            except (OSError, ValueError):
                return
            if ready:
                try:
                    data = os.read(self.pty.master, 1024)
                except OSError:
                    data = b""
                if self.faults.disconnect or not self._client_baud_matches():
                    data = b""
                for byte in data:
                    if byte == ESC:
                        self.streaming = False
                        buf.clear()
                    elif byte == 0x0D:
                        line = buf.decode("ascii", errors="replace").strip()
                        buf.clear()
                        self.handle(line)
                        next_sample = time.monotonic()
                    elif byte != 0x0A:
                        buf.append(byte)
            if self.streaming and time.monotonic() >= next_sample:
                next_sample = max(next_sample + 1.0 / self.rate_sps, time.monotonic() - 1.0)
                self._send(self._sample())

    def close(self) -> None:
        """Stop the device thread and close the pty."""
        self._stop.set()
        self._thread.join(timeout=1.0)
        self.pty.close()
