"""``rig devices scan`` against the simulated cage's ports: every device that can identify itself is
found with its kind and model, the relay board is reported as an unknown Modbus device, an empty
port finds nothing, and the written skeleton loads and opens the cage."""

from __future__ import annotations

import argparse
import os
import re
import tty
from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pytest

from rig.bringup import add_arguments, device_names, parse_tcp, run, scan, skeleton, table
from rig.config import load_rig_config
from rig.devices import build_cage
from rig.errors import UserInputError
from sim.cage import SimulatedCage
from sim.config import load_config

pytestmark = pytest.mark.realtime


@pytest.fixture(scope="module")
def scanned(cage: SimulatedCage, devices: dict[str, Any]) -> Iterator[tuple[list[Any], list[Any]]]:
    master, slave = os.openpty()  # a port with nothing behind it
    tty.setraw(slave)
    try:
        ports = [d["path"] for d in devices.values() if d["protocol"] in ("serial", "modbus-rtu")]
        tcp = [(d["host"], d["port"]) for d in devices.values() if d["protocol"] == "modbus-tcp"]
        yield scan([*ports, os.ttyname(slave)], ["sim"], tcp, i2c_objects={"sim": cage.i2c_bus})
    finally:
        os.close(master)
        os.close(slave)


def where(devices: dict[str, Any], name: str) -> str:
    d = devices[name]
    return d["path"] if "path" in d else f"{d['host']}:{d['port']}"


def test_every_identifiable_device_is_found(
    scanned: tuple[list[Any], list[Any]], devices: dict[str, Any]
) -> None:
    found, unknown = scanned
    by_where = {f.where: f for f in found}
    expect = {
        "coil_x": ("riden-rd60xx", "RD6006P"),
        "coil_y": ("riden-rd60xx", "RD6006P"),
        "coil_z": ("riden-rd60xx", "RD6006P"),
        "trim_x": ("riden-rd60xx", "RD6006P"),
        "trim_y": ("riden-rd60xx", "RD6006P"),
        "trim_z": ("riden-rd60xx", "RD6006P"),
        "load_bus": ("riden-rd60xx", "RD6006"),
        "heater": ("riden-rd60xx", "RD6006"),
        "load_panel": ("regmap-eload", "Maynuo M9812"),
        "dut": ("hmr2300", "HMR2300"),
        "reference": ("ascii-mag", "ASCII line magnetometer"),
        "outside": ("ascii-mag", "ASCII line magnetometer"),
        "cesium": ("geometrics-cm201", "Geometrics CM-201 counter (cesium)"),
    }
    for name, (kind, model) in expect.items():
        f = by_where[where(devices, name)]
        assert (f.kind, f.model) == (kind, model), name
    assert by_where[where(devices, "dut")].serial == "0123"
    assert by_where[where(devices, "dut")].params["device_id"] == 0
    rm = [f for f in found if f.kind == "rm3100"]
    assert [(f.params["bus"], f.params["address"]) for f in rm] == [("sim", 0x20)]
    assert len(found) == len(expect) + 1  # nothing on the empty port
    # no model register: the relay board and the RTD module
    assert sorted(u.where for u in unknown) == sorted(
        where(devices, n) for n in ("polarity", "dut_temp")
    )
    text = table(found, unknown)
    assert "RD6006P" in text and "a Modbus device of no known model" in text


def test_the_skeleton_loads_and_opens_the_cage(
    scanned: tuple[list[Any], list[Any]], cage: SimulatedCage, devices: dict[str, Any],
    tmp_path: Path,
) -> None:  # fmt: skip
    found, unknown = scanned
    text = skeleton(found, unknown)
    assert "FILL IN" in text and "[cage]" in text
    path = tmp_path / "rig.toml"
    # what the user does: name the relay board the scan could not identify
    relay = next(u for u in unknown if u.params.get("port") == cage.endpoints["polarity"]["port"])
    text += (
        f'\n[devices.polarity1]\nkind = "regmap-relay"\nregmap = "relay-h-bridge"\n'
        f'protocol = "modbus-tcp"\nhost = "{relay.params["host"]}"\nport = {relay.params["port"]}\n'
    )
    # the scan never guesses which magnetometer is the reference (it once named the DUT): the
    # user names it, here the simulated reference (an ASCII line magnetometer)
    assert not re.search(r"^reference\s*=", text, re.M)
    ref = next(n for n, f in zip(device_names(found), found, strict=True)
               if f.where == where(devices, "reference"))  # fmt: skip
    text = re.sub(r'^# reference = "\w+"', f'reference = "{ref}"', text, flags=re.M)
    path.write_text(text.replace('# polarity = "polarity1"', 'polarity = "polarity1"'))
    cfg = load_rig_config(path)
    assert cfg.cage is not None and cfg.cage.reference == ref
    assert cfg.cage.scalar == "scalar1"  # a total-field sensor is unambiguous: named for the user
    assert {d.kind for d in cfg.devices.values()} >= {"riden-rd60xx", "hmr2300", "rm3100"}
    with ExitStack() as stack:
        controller = build_cage(cfg, stack, cage.i2c_bus)
        controller.set_currents([0.1, 0.0, 0.0])
    assert not any(s.output for s in cage.physics.supplies.values())


def test_the_command_writes_a_loadable_skeleton(
    devices: dict[str, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    out = tmp_path / "rig.toml"
    d = devices["load_bus"]
    t = devices["load_panel"]
    args = parser.parse_args(
        [
            "--only-given",
            "--port",
            d["path"],
            "--tcp",
            f"{t['host']}:{t['port']}",
            "--write",
            str(out),
        ]
    )
    assert run(args) == 0
    printed = capsys.readouterr().out
    assert "riden-rd60xx" in printed and "regmap-eload" in printed and f"wrote {out}" in printed
    cfg = load_rig_config(out)  # no cage section with fewer than three supplies
    assert cfg.cage is None and set(cfg.devices) == {"psu1", "load1"}
    with pytest.raises(UserInputError, match="exists"):
        run(args)
    # issue 51: a link planted at the path (here dangling) is refused before the scan, and its
    # target is not created
    planted = tmp_path / "planted.toml"
    planted.symlink_to(tmp_path / "created-through-the-link.toml")
    args.write = planted
    with pytest.raises(UserInputError, match=r"planted\.toml: is a symbolic link.*remove it or"
                       r" choose another file name"):  # fmt: skip
        run(args)
    assert not (tmp_path / "created-through-the-link.toml").exists()


def test_bad_tcp_address_names_the_fix() -> None:
    with pytest.raises(UserInputError, match=r"--tcp nohost: write HOST:PORT"):
        parse_tcp("nohost")


def test_a_new_supply_is_found_by_its_map(tmp_path: Path) -> None:
    """A supply added as a register map only is recognized by its model register."""
    text = Path(load_config().source).read_text(encoding="utf-8")
    text = text.replace('name = "coil_y"\nkind = "riden-rd60xx"\nmodel_id = 60065',
                        'name = "coil_y"\nkind = "regmap"\nregmap = "hm310p"')  # fmt: skip
    path = tmp_path / "cage.toml"
    path.write_text(text)
    with SimulatedCage(load_config(path)) as sim:
        d = sim.endpoints_document()["devices"]["coil_y"]
        found, _ = scan([d["path"]], timeout_s=0.2)
    assert [(f.kind, f.model, f.params["regmap"]) for f in found] == [
        ("regmap-supply", "Hanmatek HM310P", "hm310p")
    ]


def test_nothing_answering_says_what_to_check(capsys: pytest.CaptureFixture[str]) -> None:
    master, slave = os.openpty()
    tty.setraw(slave)
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    try:
        assert run(parser.parse_args(["--only-given", "--port", os.ttyname(slave)])) == 1
    finally:
        os.close(master)
        os.close(slave)
    assert "nothing answered; check power and cables" in capsys.readouterr().err
