"""A simulated external flight computer for the closed loop's tests (docs/hil.md): B-dot over UDP,
in the protocol the rig speaks (CCSDS space packets: readings in, dipoles out), written apart from
the rig's side so each checks the other.

    python -m sim.flight_computer --port 5005 [--gain 0.38] [--max-dipole 0.2]
"""

from __future__ import annotations

import argparse
import socket
import struct
import threading

import numpy as np

_HEADER = struct.Struct(">HHH")
READINGS_APID, DIPOLE_APID = 0x0A1, 0x0A2


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
    args = parser.parse_args(argv)
    computer = BDotComputer(args.gain, args.max_dipole, args.port, args.host)
    print(f"flight computer: B-dot on udp://{args.host}:{computer.port}", flush=True)
    try:
        computer._serve()
    except KeyboardInterrupt:
        pass
    finally:
        computer.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
