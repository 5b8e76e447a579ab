"""The Cage page says where every device is: host and port with the Modbus unit id, a serial
port, an I2C bus and address (it showed nothing for serial devices and no host for TCP ones)."""

from __future__ import annotations

from pathlib import Path

from rig.web.app import cage_status

RIG = """
[devices.coil_x]
kind = "riden-rd60xx"
protocol = "modbus-tcp"
host = "192.168.1.50"
port = 502
device_id = 3
[devices.load1]
kind = "riden-rd60xx"
protocol = "modbus-rtu"
path = "/dev/ttyUSB3"
device_id = 2
[devices.dut]
kind = "hmr2300"
protocol = "serial"
path = "/dev/ttyUSB0"
[devices.ref]
kind = "rm3100"
protocol = "i2c"
bus = 1
address = 0x20
"""


def test_every_device_has_its_address(tmp_path: Path) -> None:
    (tmp_path / "rig.toml").write_text(RIG)
    status = cage_status(tmp_path / "rig.toml")
    assert status is not None
    where = {d["name"]: d["where"] for d in status["devices"]}
    assert where == {"coil_x": "192.168.1.50:502 id 3", "load1": "/dev/ttyUSB3 id 2",
                     "dut": "/dev/ttyUSB0", "ref": "i2c bus 1 address 0x20"}  # fmt: skip
