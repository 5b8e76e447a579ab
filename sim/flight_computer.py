"""A simulated external flight computer for the closed loop's tests (docs/hil.md): B-dot over UDP
or a serial line, in the protocol the rig speaks (CCSDS space packets: readings in, dipoles out;
on a serial line each after the sync marker 1A CF FC 1D), written apart from the rig's side so
each checks the other.

    python -m sim.flight_computer --port 5005 [--gain 0.38] [--max-dipole 0.2]
    python -m sim.flight_computer --pty        (prints the serial port to give the rig)
"""

from __future__ import annotations

import argparse
import contextlib
import os
import socket
import struct
import threading
import tty

import numpy as np

from sim.own_processor import instrument_priority

_HEADER = struct.Struct(">HHH")
READINGS_APID, DIPOLE_APID = 0x0A1, 0x0A2
SYNC = b"\x1a\xcf\xfc\x1d"


class BDotComputer:
    """Answers each readings packet with ``-gain dB/dt`` (clipped), from the last two readings."""

    def __init__(self, gain_am2_per_ut_s: float, max_dipole_am2: float, port: int = 0,
                 host: str = "127.0.0.1") -> None:  # fmt: skip
        self.gain, self.max_dipole = gain_am2_per_ut_s, max_dipole_am2
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, port))
        self.port = int(self.sock.getsockname()[1])
        self._last: tuple[float, np.ndarray] | None = None
        self._thread = threading.Thread(target=self._serve, name="flight-computer", daemon=True)

    def start(self) -> BDotComputer:
        with instrument_priority():  # a flight computer has its own processor
            self._thread.start()
        return self

    def _serve(self) -> None:
        while True:
            try:
                raw, peer = self.sock.recvfrom(2048)
            except OSError:
                return  # closed
            answer = self._answer(raw)
            if answer is not None:  # anything else goes unanswered, as on a flight computer
                self.sock.sendto(answer, peer)

    def _answer(self, raw: bytes) -> bytes | None:
        if len(raw) != _HEADER.size + 32:
            return None
        word1, word2, length = _HEADER.unpack_from(raw)
        if word1 >> 11 != 0 or word1 & 0x7FF != READINGS_APID or length != 31:
            return None  # version 0, telemetry, no secondary header, the readings APID
        t, x, y, z = struct.unpack_from(">4d", raw, _HEADER.size)
        field = np.array([x, y, z])
        dipole = np.zeros(3)
        if self._last is not None and t > self._last[0]:
            rate = (field - self._last[1]) / (t - self._last[0])
            dipole = np.clip(-self.gain * rate, -self.max_dipole, self.max_dipole)
        self._last = (t, field)
        header = _HEADER.pack(1 << 12 | DIPOLE_APID, 0b11 << 14 | (word2 & 0x3FFF), 23)
        return header + struct.pack(">3d", *dipole)

    def close(self) -> None:
        self.sock.close()


class SerialFrontEnd:
    """The same B-dot on a serial line: the flight computer's end of a pseudo-terminal (its
    other end, :attr:`port`, is what the rig opens), packets found by their sync marker."""

    def __init__(self, computer: BDotComputer) -> None:
        self.computer = computer
        self.fd, follower = os.openpty()
        tty.setraw(follower)  # bytes as they are: no echo, no line editing on the rig's end
        self.port = os.ttyname(follower)
        self._follower = follower
        self._buf = b""
        self._thread = threading.Thread(target=self.serve, name="flight-computer-serial",
                                        daemon=True)  # fmt: skip

    def start(self) -> SerialFrontEnd:
        with instrument_priority():  # a flight computer has its own processor
            self._thread.start()
        return self

    def serve(self) -> None:
        while True:
            try:
                chunk = os.read(self.fd, 4096)
            except OSError:
                return  # closed
            if not chunk:
                return
            self._buf += chunk
            for packet in self._packets():
                answer = self.computer._answer(packet)
                if answer is not None:
                    os.write(self.fd, SYNC + answer)

    def _packets(self) -> list[bytes]:
        out = []
        while (at := self._buf.find(SYNC)) >= 0:
            head = at + len(SYNC)
            if len(self._buf) < head + _HEADER.size:
                break
            end = head + _HEADER.size + _HEADER.unpack_from(self._buf, head)[2] + 1
            if len(self._buf) < end:
                break
            out.append(self._buf[head:end])
            self._buf = self._buf[end:]
        return out

    def close(self) -> None:
        for fd in (self.fd, self._follower):
            with contextlib.suppress(OSError):
                os.close(fd)
        self.computer.close()  # its UDP socket, unused on a serial line


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="a simulated B-dot flight computer on UDP")
    parser.add_argument(
        "--port", type=int, default=5005, help="UDP port to answer on (default 5005)"
    )
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    parser.add_argument(
        "--gain", type=float, default=0.38, help="B-dot gain, A m^2 per uT/s (default 0.38)"
    )
    parser.add_argument(
        "--max-dipole",
        type=float,
        default=0.2,
        help="each rod's largest dipole, A m^2 (default 0.2)",
    )
    parser.add_argument(
        "--pty",
        action="store_true",
        help="answer on a new pseudo-terminal (a serial line) instead of UDP; prints its path",
    )
    args = parser.parse_args(argv)
    computer = BDotComputer(args.gain, args.max_dipole, args.port, args.host)
    serial = SerialFrontEnd(computer) if args.pty else None
    where = f"serial://{serial.port}" if serial else f"udp://{args.host}:{computer.port}"
    print(f"flight computer: B-dot on {where}", flush=True)
    try:
        serial.serve() if serial else computer._serve()
    except KeyboardInterrupt:
        pass
    finally:
        computer.close()
        if serial:
            serial.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
