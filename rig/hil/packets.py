"""The flight computer protocol (docs/hil.md): CCSDS space packets (CCSDS 133.0-B-2), one per UDP
datagram.

* **Readings to the flight computer**: a telemetry packet (type 0), APID :data:`READINGS_APID`, its
  sequence count the control period's number (mod 16384); data: the loop time (s) and the
  period's mean magnetometer reading in the body frame (uT, x y z), four big-endian IEEE-754
  doubles (32 bytes).
* **Dipoles from the flight computer**: a telecommand packet (type 1), APID :data:`DIPOLE_APID`,
  the same sequence count as the readings it answers; data: the torque rods' dipoles (A m^2,
  body frame x y z), three big-endian doubles (24 bytes).

The primary header: version 0, no secondary header, sequence flags 0b11 (unsegmented), data length
= bytes of data - 1.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

READINGS_APID = 0x0A1
DIPOLE_APID = 0x0A2
HEADER = struct.Struct(">HHH")
READINGS = struct.Struct(">4d")
DIPOLE = struct.Struct(">3d")
SEQUENCE_MODULUS = 1 << 14


class PacketError(ValueError):
    """Not a packet of this protocol: what is wrong, in one phrase."""


@dataclass(frozen=True)
class Packet:
    """A decoded packet: its type (0 telemetry, 1 telecommand), APID, sequence count, data."""

    kind: int
    apid: int
    sequence: int
    data: bytes


def encode(kind: int, apid: int, sequence: int, data: bytes) -> bytes:
    """One space packet of ``data`` (1-65536 bytes)."""
    word1 = (kind & 1) << 12 | (apid & 0x7FF)
    word2 = 0b11 << 14 | (sequence % SEQUENCE_MODULUS)
    return HEADER.pack(word1, word2, len(data) - 1) + data


def decode(raw: bytes) -> Packet:
    """The packet in ``raw`` (exactly one); PacketError when it is not one."""
    if len(raw) < HEADER.size + 1:
        raise PacketError(f"{len(raw)} bytes, shorter than a packet")
    word1, word2, length = HEADER.unpack_from(raw)
    if word1 >> 13 != 0:
        raise PacketError(f"version {word1 >> 13}, not 0")
    if word1 & 0x0800:
        raise PacketError("a secondary header, which this protocol does not use")
    if len(raw) != HEADER.size + length + 1:
        raise PacketError(f"{len(raw)} bytes where the header says {HEADER.size + length + 1}")
    return Packet((word1 >> 12) & 1, word1 & 0x7FF, word2 & 0x3FFF, raw[HEADER.size :])


def readings_packet(sequence: int, t_s: float, field_ut: tuple[float, float, float]) -> bytes:
    return encode(0, READINGS_APID, sequence, READINGS.pack(t_s, *field_ut))


def dipole_of(packet: Packet) -> tuple[float, float, float]:
    """The dipoles (A m^2) of a dipole packet; PacketError for any other packet."""
    if packet.kind != 1 or packet.apid != DIPOLE_APID or len(packet.data) != DIPOLE.size:
        raise PacketError(f"not a dipole packet (type {packet.kind}, APID {packet.apid:#x},"
                          f" {len(packet.data)} bytes of data)")  # fmt: skip
    x, y, z = DIPOLE.unpack(packet.data)
    return float(x), float(y), float(z)
