"""HMR2300 continuous stream on the simulated cage: 154 samples/s binary at 19200 baud.

Opens the simulated DUT's pty with pyserial exactly as a driver would, switches to binary at
154 sps, streams for --seconds (default 60), stops the stream with ESC and counts frames: every
7-byte frame must end in CR at its stride (misaligned: one that does not) and every frame the
device sent must arrive (lost: sent minus received). Prints the rate received per second of wall
time and the rate on the device's own sample clock, against the datasheet's 154 sps and the line
capacity at 19200 baud (7 bytes x 10 bits: 274 frames/s).

By default the simulated cage runs in a child process, as ``rig demo`` runs ``rig sim``, so the
device has its own interpreter; ``--in-process`` runs it in this process beside the reader (as the
wire tests do). The reader blocks for the first byte and then takes what arrived in 20 ms chunks
(a rig sampler's pace), so it never competes with the device for the processor.

Usage: python bench/bench_hmr2300_stream.py [--seconds S] [--in-process]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from typing import IO, Any, Protocol

import serial

from rig.child_process import start_child, stop_child
from sim.cage import SimulatedCage
from sim.config import load_config
from sim.hmr2300 import Hmr2300

RATE_SPS = 154
FRAME = 7  # bytes
CAPACITY = 19200 / (FRAME * 10)  # frames/s


def device_state(device: Hmr2300) -> dict[str, Any]:
    """The simulated device's counters and sample clock (times in s, ``time.monotonic``)."""
    sent, due = device.stream_clock
    return {"samples_sent": device.samples_sent, "last_sent": sent, "last_due_s": due,
            "start_s": device.stream_start_s, "streaming": device.streaming,
            "skipped": device.samples_skipped, "overrun_bytes": device.bytes_overrun}  # fmt: skip


def serve_device() -> int:
    """Child side: run the simulated cage; one JSON line per request on stdin ('' ends it)."""
    with SimulatedCage(load_config()) as cage:
        device = cage.serial_devices["dut"]
        assert isinstance(device, Hmr2300)
        print(json.dumps({"path": device.path}), flush=True)
        for _ in sys.stdin:
            print(json.dumps(device_state(device)), flush=True)
    return 0


class Device(Protocol):
    path: str

    def state(self) -> dict[str, Any]: ...

    def close(self) -> None: ...


class InProcess:
    """The simulated cage in this process."""

    def __init__(self) -> None:
        self.cage = SimulatedCage(load_config())
        self.cage.start()
        device = self.cage.serial_devices["dut"]
        assert isinstance(device, Hmr2300)
        self.device = device
        self.path = device.path

    def state(self) -> dict[str, Any]:
        return device_state(self.device)

    def close(self) -> None:
        self.cage.stop()


class ChildProcess:
    """The simulated cage in a child process that dies with this one."""

    def __init__(self) -> None:
        self.proc = start_child([sys.executable, os.path.abspath(__file__), "--serve-device"],
                                stdin=subprocess.PIPE, stdout=subprocess.PIPE)  # fmt: skip
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self._in: IO[bytes] = self.proc.stdin
        self._out: IO[bytes] = self.proc.stdout
        self.path = str(json.loads(self._out.readline())["path"])

    def state(self) -> dict[str, Any]:
        self._in.write(b"?\n")
        self._in.flush()
        return dict(json.loads(self._out.readline()))

    def close(self) -> None:
        self._in.close()  # end of requests: the child stops its cage and exits
        try:
            self.proc.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            stop_child(self.proc, wait_s=5.0)


def command(port: serial.Serial, text: str) -> bytes:
    """Send a command, return its reply line (waits up to 30 s: the machine may be loaded)."""
    port.write(text.encode() + b"\r")
    reply = b""
    deadline = time.monotonic() + 30.0
    while not reply.endswith(b"\r") and time.monotonic() < deadline:
        reply += port.read_until(b"\r")
    return bytes(reply)


def stream(dev: Device, seconds: float) -> dict[str, Any]:
    """Stream for ``seconds`` of wall time; the counts and clocks (s)."""
    port = serial.Serial(dev.path, 19200, timeout=1.0)
    try:
        for text, reply in (("*00WE", b"OK\r"), ("*00B", b"BINARY ON\r"), ("*00WE", b"OK\r"),
                            ("*00R=154", b"OK\r")):  # fmt: skip
            assert command(port, text) == reply, text
        before = dev.state()
        buf = bytearray()
        port.write(b"*00C\r")
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            buf += port.read(1)  # blocks until data (at most 1 s)
            time.sleep(0.02)
            buf += port.read(port.in_waiting)
        t_esc = time.monotonic()
        frames_by_esc = len(buf) // FRAME
        port.write(b"\x1b")
        deadline = time.monotonic() + 30.0
        while (after := dev.state())["streaming"] and time.monotonic() < deadline:
            time.sleep(0.01)
        sent = after["samples_sent"] - before["samples_sent"]
        while len(buf) < FRAME * sent and time.monotonic() < deadline:
            buf += port.read(FRAME * sent - len(buf))
        buf += port.read(port.in_waiting)
    finally:
        port.close()
    frames = len(buf) // FRAME
    return {
        "frames": frames,
        "sent": sent,
        "lost": sent - frames,
        "misaligned": sum(1 for i in range(frames) if buf[FRAME * i + FRAME - 1] != 0x0D),
        "trailing": len(buf) % FRAME,
        "wall_rate": frames_by_esc / (t_esc - t0),
        "device_rate": (sent - 1) / (after["last_due_s"] - after["start_s"]),
        "skipped": after["skipped"] - before["skipped"],
        "overrun_bytes": after["overrun_bytes"] - before["overrun_bytes"],
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--in-process", action="store_true", help="run the simulator in this process")
    ap.add_argument("--serve-device", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.serve_device:
        return serve_device()
    dev: Device = InProcess() if args.in_process else ChildProcess()
    try:
        r = stream(dev, args.seconds)
    finally:
        dev.close()
    where = "in this process" if args.in_process else "in a child process"
    print(f"simulator {where}; streamed {args.seconds:.0f} s: {r['frames']} frames received,"
          f" {r['sent']} sent by the device, {r['lost']} lost, {r['misaligned']} misaligned,"
          f" {r['trailing']} trailing bytes, {r['skipped']} slots skipped,"
          f" {r['overrun_bytes']} bytes overrun")  # fmt: skip
    for label, rate in (("received", r["wall_rate"]), ("device clock", r["device_rate"])):
        print(f"rate ({label}) {rate:.1f} samples/s: {rate / RATE_SPS:.3f} of the datasheet's"
              f" {RATE_SPS} sps, {rate / CAPACITY:.3f} of the 19200-baud line capacity"
              f" ({CAPACITY:.0f} frames/s)")  # fmt: skip
    ok = (
        r["lost"] == 0
        and r["misaligned"] == 0
        and r["trailing"] == 0
        and abs(r["device_rate"] / RATE_SPS - 1) <= 0.01
        and r["wall_rate"] >= 0.99 * RATE_SPS
    )
    print("PASS" if ok else "MISS")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
