"""An external flight computer as the flight software under test: the readings go out and the
dipoles come back over UDP or a serial line (:mod:`rig.hil.flight_links`) in the protocol of
:mod:`rig.hil.packets` (docs/hil.md).

Each control period the mean reading goes out with the period's number as the sequence count;
the answer with the same count is awaited for at most ``reply_timeout_s`` (wall clock: the flight
computer is another machine). No answer in time, or a packet that is not one: the rods keep the
dipoles they had, and the miss is counted (``missed``) with the first reason kept (``problem``),
so a loop with a silent flight computer is flagged, never silently open.
"""

from __future__ import annotations

import math
import time

import numpy as np
import numpy.typing as npt

from rig.hil.flight_links import parse_address
from rig.hil.packets import SEQUENCE_MODULUS, PacketError, decode, dipole_of, readings_packet

Array = npt.NDArray[np.float64]


class ExternalFlightComputer:
    """The flight software at ``address`` (``udp://HOST:PORT`` or ``serial:///dev/PORT``)."""

    def __init__(self, address: str, reply_timeout_s: float) -> None:
        self.address = parse_address(address)
        self.reply_timeout_s = reply_timeout_s
        self.link = self.address.open()
        self.sequence = 0
        self.dipole_am2 = np.zeros(3)
        self.answered = 0
        self.missed = 0
        self.problem: str | None = None
        self.round_trips_s: list[float] = []

    def dipole(self, field_ut: Array, t_s: float) -> Array:
        """Send the period's reading, wait for its answer; the dipoles (A m^2) to hold."""
        seq = self.sequence % SEQUENCE_MODULUS
        self.sequence += 1
        sent = time.monotonic()
        try:
            self.link.send(readings_packet(seq, t_s, (float(field_ut[0]), float(field_ut[1]),
                                                      float(field_ut[2]))))  # fmt: skip
            answer = self._answer(seq, sent + self.reply_timeout_s)
        except OSError as exc:
            answer = f"the link failed ({exc})"
        if isinstance(answer, str):
            self.missed += 1
            self.problem = self.problem or answer
        else:
            self.answered += 1
            self.round_trips_s.append(time.monotonic() - sent)
            self.dipole_am2 = answer
        return self.dipole_am2.copy()

    def _answer(self, seq: int, deadline: float) -> Array | str:
        """The dipoles answering ``seq``, or why there are none (an older answer is passed by)."""
        while (raw := self.link.receive(deadline)) is not None:
            try:
                packet = decode(raw)
                dipole = dipole_of(packet)
            except PacketError as exc:
                return f"a packet that is not a dipole packet: {exc}"
            if packet.sequence == seq:
                if not all(math.isfinite(v) for v in dipole):
                    return f"a dipole that is not a number: {dipole}"
                return np.array(dipole, float)
        return f"no answer within {1000.0 * self.reply_timeout_s:.0f} ms"

    def close(self) -> None:
        self.link.close()
