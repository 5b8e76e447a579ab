"""`rig cage` against a `rig sim` process on the wall clock: a field held, limits, safe state."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from pymodbus.client import ModbusTcpClient

from tests.simproc import sim_process

pytestmark = pytest.mark.realtime


@pytest.fixture(scope="module")
def sim_rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, dict]]:  # type: ignore[type-arg]
    with sim_process(tmp_path_factory.mktemp("simrig")) as sim:
        yield sim


def rig(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "rig.cli", *args], capture_output=True, text=True, timeout=120
    )


def outputs_on(devices: dict) -> list[bool]:  # type: ignore[type-arg]
    states = []
    for name in ("coil_x", "coil_z"):
        d = devices[name]
        with ModbusTcpClient(d["host"], port=d["port"]) as c:
            states.append(bool(c.read_holding_registers(18, count=1, device_id=1).registers[0]))
    return states


def test_set_field_then_every_output_off(sim_rig: tuple[Path, dict]) -> None:  # type: ignore[type-arg]
    """Another process's cage on loopback and ptys: the field set from the nameplate (no
    characterization yet), held, then ramped down and off as read back over the wire. The
    characterization and the trimmed field run in simulated time
    (tests/cage/test_cage_command_simulated.py)."""
    rig_toml, devices = sim_rig
    proc = rig("cage", "set-field", "10", "-5", "5", "--hold", "0.3", "--rig-config", str(rig_toml))
    assert proc.returncode == 0, proc.stderr
    assert "holding" in proc.stdout and "outputs ramped down and off" in proc.stdout, proc.stdout
    assert outputs_on(devices) == [False, False]


def test_limits_and_bad_config_are_one_line_errors(
    sim_rig: tuple[Path, dict], tmp_path: Path
) -> None:  # type: ignore[type-arg]
    rig_toml, devices = sim_rig
    proc = rig("cage", "set-field", "100", "100", "0", "--rig-config", str(rig_toml))
    assert proc.returncode == 2 and "beyond the 120 uT field limit" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert outputs_on(devices) == [False, False]
    bad = tmp_path / "rig.toml"
    bad.write_text(rig_toml.read_text().replace('kind = "riden-rd60xx"', 'kind = "riden"', 1))
    proc = rig("cage", "set-field", "0", "0", "0", "--rig-config", str(bad))
    assert proc.returncode == 2 and "'riden' is not one of" in proc.stderr
