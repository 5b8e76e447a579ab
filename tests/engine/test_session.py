"""The rig session: devices opened together, every output safe on every way out."""

from __future__ import annotations

from contextlib import nullcontext
from pathlib import Path

import numpy as np
import pytest

from rig.config import load_rig_config
from rig.engine.session import RigSession, switch_off_every_output
from rig.errors import UserInputError
from tests.simcage import sim_cage


@pytest.mark.parametrize("ending", ["normal", "error", "ctrl-c"])
def test_every_output_is_off_however_the_session_ends(tmp_path: Path, ending: str) -> None:
    with sim_cage(tmp_path) as (cage, rig_toml):
        rc = load_rig_config(rig_toml)
        supplies = cage.physics.supplies
        expect = (
            pytest.raises((RuntimeError, KeyboardInterrupt))
            if ending != "normal"
            else nullcontext()
        )
        with expect, RigSession(rc, i2c_bus=cage.i2c_bus) as rig:
            rig.cage().set_field(np.array([20.0, -10.0, 30.0]))
            rig.load("load_bus").set_current(1.0)
            assert rig.magnetometer("reference") is rig.controller.reference  # type: ignore[union-attr]
            assert rig.magnetometer("dut").read() is not None
            assert sum(s.output for s in supplies.values()) >= 4  # three coils and the load
            if ending == "error":
                raise RuntimeError("a step failed")
            if ending == "ctrl-c":
                raise KeyboardInterrupt
        assert not any(s.output for s in supplies.values())


def test_an_unknown_device_is_one_line_naming_the_file(tmp_path: Path) -> None:
    with sim_cage(tmp_path) as (cage, rig_toml):
        rc = load_rig_config(rig_toml)
        with (
            RigSession(rc) as rig,
            pytest.raises(UserInputError, match=r"rig.toml: no device 'load_bsu' for the load"),
        ):
            rig.load("load_bsu")
        for s in cage.physics.supplies.values():
            s.set_current(0.5)
            s.set_output(True)
        cage.faults[
            "load_panel"
        ].silent = True  # one that does not answer is named, the rest go off
        done, problems, _ = switch_off_every_output(rc)
        assert "load_panel" not in done and problems and problems[0].startswith("load_panel")
        assert not any(s.output for n, s in cage.physics.supplies.items() if n != "load_panel")


def test_devices_on_one_wire_share_a_link_for_the_safe_state(tmp_path: Path) -> None:
    """The safe state switches links off in parallel and the devices on one link in turn: a
    by-id name and the port it points to are one RS-485 bus, an I2C bus is one whatever the
    address, a TCP endpoint is one whatever the unit id."""
    from rig.config import DeviceConfig
    from rig.engine.interlock import wire_address, wire_link

    port = tmp_path / "ttyUSB0"
    port.touch()
    by_id = tmp_path / "usb-FTDI-if00"
    by_id.symlink_to(port)

    def dev(protocol: str, **params: object) -> DeviceConfig:
        return DeviceConfig("d", "regmap-supply", protocol, dict(params))

    assert wire_link(dev("modbus-rtu", path=str(by_id), device_id=1)) == wire_link(
        dev("modbus-rtu", path=str(port), device_id=2)
    )
    assert wire_link(dev("i2c", address=0x20)) == wire_link(dev("i2c", bus=1, address=0x1C))
    assert wire_link(dev("modbus-tcp", host="h", device_id=1)) == wire_link(
        dev("modbus-tcp", host="h", port=502, device_id=3)
    )
    assert wire_link(dev("modbus-tcp", host="h")) != wire_link(
        dev("modbus-tcp", host="h", port=5020)
    )
    # the interlock's addresses are the link plus the unit on it, as before
    assert wire_address(dev("modbus-rtu", path=str(by_id), device_id=2)) == (
        f"modbus-rtu {port.resolve()} id 2"
    )
    assert wire_address(dev("i2c", bus=1, address=0x20)) == "i2c bus 1 address 0x20"
