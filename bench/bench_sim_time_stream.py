"""How fast the simulated cage runs in simulated time (ADR 0038): the HMR2300's binary stream at
154 sps and 19200 Bd for --seconds of simulated time (default 60), read frame by frame through
pyserial on ``simpipe://dut`` while the whole default cage runs (Modbus servers, the reference
magnetometers, the cesium counter). Prints the wall time it took, the ratio, the frames received
against the device's count and the clock's turns (hand-overs between its threads).

Nothing here waits on the wall clock, so the frame count and the transcript are the same on any
machine and under any load; only the wall time is the computer's.

Usage: ``.venv/bin/python bench/bench_sim_time_stream.py [--seconds S]``
"""

from __future__ import annotations

import argparse
import time

import serial

import timebase
from sim.cage import SimulatedCage
from sim.config import load_config
from sim.hmr2300 import Hmr2300

FRAME = 7  # bytes of a binary sample


def stream(seconds: float) -> dict[str, float]:
    """Stream for ``seconds`` of simulated time; what it took and what arrived."""
    started = time.perf_counter()
    with timebase.simulated() as clock:
        cage = SimulatedCage(load_config())
        devices = cage.start()["devices"]
        try:
            device = cage.serial_devices["dut"]
            assert isinstance(device, Hmr2300)
            port = serial.serial_for_url(devices["dut"]["path"], baudrate=19200, timeout=0.5)
            port.write(b"*99WE\r*99B\r*99WE\r*99R=154\r")
            timebase.sleep(0.1)
            port.reset_input_buffer()
            port.write(b"*99C\r")
            frames, t_end = 0, timebase.monotonic() + seconds
            while timebase.monotonic() < t_end:
                frames += len(port.read(FRAME)) // FRAME
            port.write(b"\x1b")
            sent = device.samples_sent
        finally:
            cage.stop()
        turns = clock.switches
    wall = time.perf_counter() - started
    return {"simulated_s": seconds, "wall_s": wall, "frames": frames, "sent": sent, "turns": turns}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="simulated seconds to stream")
    args = parser.parse_args()
    r = stream(args.seconds)
    print(f"{r['simulated_s']:g} s of simulated HMR2300 streaming took {r['wall_s']:.2f} s of wall"
          f" time ({r['simulated_s'] / r['wall_s']:.1f}x real time); {r['frames']:.0f} frames"
          f" received of {r['sent']:.0f} sent ({r['frames'] / r['simulated_s']:.1f} per simulated"
          f" s); {r['turns']:.0f} turns of the clock")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
