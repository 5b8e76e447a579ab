"""`rig sim` as a standalone process: endpoints file, loopback only, clean stop on Ctrl-C."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest
from pymodbus.client import ModbusTcpClient

from sim.own_processor import INSTRUMENT_NICE
from tests.sim.nice import nice_of

pytestmark = pytest.mark.realtime


def test_rig_sim_publishes_endpoints_and_stops_on_sigint(tmp_path: Path) -> None:
    ep = tmp_path / "endpoints.json"
    cfg = tmp_path / "rig.toml"
    proc = subprocess.Popen(
        [sys.executable, "-m", "rig.cli", "sim", "--endpoints-json", str(ep), "--rig-config", str(cfg)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 20
        while not ep.exists():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline
            time.sleep(0.05)
        devices = json.loads(ep.read_text())["devices"]
        assert {"coil_x", "coil_y", "coil_z", "dut", "reference", "rm3100"} <= set(devices)
        kinds = {d["kind"] for d in devices.values()}
        assert {"riden-rd60xx", "hmr2300", "ascii-mag", "rm3100"} <= kinds
        for dev in devices.values():
            if dev["protocol"] == "modbus-tcp":
                assert dev["host"] == "127.0.0.1" and dev["port"] > 0
            if dev["protocol"] in ("serial", "modbus-rtu"):
                assert Path(dev["path"]).exists() and dev["baudrate"] > 0
        x = devices["coil_x"]
        with ModbusTcpClient(x["host"], port=x["port"], timeout=2) as c:
            assert c.read_holding_registers(0, count=1, device_id=x["device_id"]).registers == [
                60065
            ]
            assert not c.write_register(18, 1, device_id=1).isError()  # output on
        assert f"port = {x['port']}" in cfg.read_text()
        # its instruments share this computer's cores: a stream judged stalled after 5 s, not 1.5
        written = tomllib.loads(cfg.read_text())["devices"]
        assert written["dut"]["stall_after_s"] == written["reference"]["stall_after_s"] == 5.0
        assert "stall_after_s" not in written["cesium"]  # a counter, not a vector stream
        # its instruments' threads run at a raised priority (sim.own_processor), the main one not
        nices = sorted(nice_of(int(tid), proc.pid) for tid in os.listdir(f"/proc/{proc.pid}/task"))
        assert nices[-1] == 0 and nices.count(INSTRUMENT_NICE if os.geteuid() == 0 else 0) >= 4
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "stopped; all outputs off" in out
    assert ("normal CPU priority" in out) is (os.geteuid() != 0)
    assert "Traceback" not in err


def test_rig_sim_bad_config_is_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "cage.toml"
    bad.write_text("seed = 1\n[cage]\n")
    proc = subprocess.run([sys.executable, "-m", "rig.cli", "sim", "--config", str(bad)],
                          capture_output=True, text=True, timeout=30)  # fmt: skip
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1 and "cage.toml" in proc.stderr
