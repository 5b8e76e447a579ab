"""HMR2300 continuous stream on the simulated cage: 154 samples/s binary at 19200 baud.

Opens the simulated DUT's pty with pyserial exactly as a driver would, switches to binary at
154 sps, streams for --seconds (default 60), and counts frames: every 7-byte frame must end in CR at
its stride (no resynchronisation needed) and every frame the device sent must arrive. Prints the
achieved rate against the datasheet's 154 sps and against the line capacity at 19200 baud
(7 bytes x 10 bits = 274 frames/s) measured in the same run.

Usage: python bench/bench_hmr2300_stream.py [--seconds S]
"""

from __future__ import annotations

import argparse
import sys
import time

import serial

from sim.cage import SimulatedCage
from sim.config import load_config


def command(port: serial.Serial, text: str) -> bytes:
    port.write(text.encode() + b"\r")
    return bytes(port.read_until(b"\r"))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seconds", type=float, default=60.0)
    args = ap.parse_args()
    with SimulatedCage(load_config()) as cage:
        dev = cage.endpoints_document()["devices"]["dut"]
        device = cage.serial_devices["dut"]
        port = serial.Serial(dev["path"], 19200, timeout=1.0)
        for text, reply in (("*00WE", b"OK\r"), ("*00B", b"BINARY ON\r"), ("*00WE", b"OK\r"),
                            ("*00R=154", b"OK\r")):  # fmt: skip
            assert command(port, text) == reply, text
        sent_before = device.samples_sent
        port.write(b"*00C\r")
        buf = bytearray()
        t0 = time.monotonic()
        while time.monotonic() - t0 < args.seconds:
            buf += port.read(max(1, port.in_waiting))
        elapsed = time.monotonic() - t0
        port.write(b"\x1b")
        time.sleep(0.2)
        buf += port.read(port.in_waiting)
        sent = device.samples_sent - sent_before
        port.close()
    frames = len(buf) // 7
    misaligned = sum(1 for i in range(frames) if buf[7 * i + 6] != 0x0D)
    lost = sent - frames
    rate = frames / elapsed
    capacity = 19200 / 70
    print(f"streamed {args.seconds:.0f} s: {frames} frames received, {sent} sent by the device,"
          f" {lost} lost, {misaligned} misaligned, {len(buf) % 7} trailing bytes")  # fmt: skip
    print(f"rate {rate:.1f} samples/s: {rate / 154:.3f} of the datasheet's 154 sps,"
          f" {rate / capacity:.3f} of the 19200-baud line capacity ({capacity:.0f} frames/s)")  # fmt: skip
    ok = lost == 0 and misaligned == 0 and rate >= 0.99 * 154
    print("PASS" if ok else "MISS")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
