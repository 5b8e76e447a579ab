"""The simulated HMR2300 streams at the datasheet rate and the real driver receives every frame.

Nothing here measures our own scheduling: the rate is taken on the device's sample clock (slot
times it reports, s) and completeness by counting frames received against frames the device
says it put on the line, so the test holds on a machine whose cores are busy with other work.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest

from drivers.mag.hmr2300 import ESC
from drivers.mag.hmr2300 import Hmr2300 as Hmr2300Driver
from sim.cage import SimulatedCage
from sim.hmr2300 import Hmr2300

pytestmark = pytest.mark.realtime

STREAM_S = 5.0  # device time
DEADLINE_S = 120.0  # wall time, only against a hang


def test_binary_stream_at_154_sps_delivers_every_frame(
    devices: dict[str, Any], cage: SimulatedCage
) -> None:
    device = cage.serial_devices["dut"]
    assert isinstance(device, Hmr2300)
    hmr = Hmr2300Driver(devices["dut"]["path"], baudrate=devices["dut"]["baudrate"])
    try:
        hmr.set_binary(True)
        hmr.set_rate(154)
        sent0, skipped0, overrun0 = (
            device.samples_sent,
            device.samples_skipped,
            device.bytes_overrun,
        )
        deadline = time.monotonic() + DEADLINE_S
        hmr.start_stream()
        frames: list[tuple[float, float, float]] = []
        while time.monotonic() < deadline:
            frames += hmr.read_stream(max_wait_s=1.0)
            if device.stream_clock[1] - device.stream_start_s >= STREAM_S:
                break
        # Stop the device with ESC but keep what is already on the line (stop_stream discards it).
        hmr.port.write(ESC)
        while device.streaming and time.monotonic() < deadline:
            time.sleep(0.01)
        assert not device.streaming, "the device did not see ESC"
        sent = device.samples_sent - sent0
        while len(frames) < sent and time.monotonic() < deadline:
            frames += hmr.read_stream(max_wait_s=1.0)
        last = device.stream_clock
        assert hmr.read_stream(max_wait_s=0.2) == []  # nothing after the last frame sent
    finally:
        hmr.close()

    assert len(frames) == sent, f"{sent} frames sent, {len(frames)} received"
    assert hmr.resyncs == 0
    assert device.samples_skipped == skipped0
    assert device.bytes_overrun == overrun0
    # Slot 0 is due at stream_start_s; the last frame sent is number `sent`, due at last[1].
    assert last[0] - sent0 == sent
    span_s = last[1] - device.stream_start_s
    assert span_s >= STREAM_S
    rate = (sent - 1) / span_s
    assert rate == pytest.approx(154.0, rel=0.01)
    values = np.array(frames)
    assert np.all(np.abs(values) < 200.0)  # plausible fields (uT), not shifted bytes
