"""`rig check` holds every supply's and load's protection levels (OVP, OCP, OPP) against the rig
file's limits for that output (issue 53): the levels the file sets (``ovp_v``, ``ocp_a``,
``opp_w``, written when the rig opens the output) without opening anything, and with
``--protections`` the levels the instruments hold. A level above its limit is a warning naming
where it is, its value, the limit and the fix."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest

from rig.cli import main
from rig.config import load_rig_config
from rig.devices import open_load
from sim.cage import SimulatedCage
from tests.conformance.simcage import cage_with
from tests.sim.rig_toml import rig_toml

PROC = "procedure: T\nsteps:\n  - set_field: {field_ut: [0, 0, 10], hold_s: 1}\n"
RIG = """
[cage]
axes = { x = "coil_x", y = "coil_y", z = "coil_z" }
max_current_a = [2.5, 2.5, 2.5]
max_field_ut = 120.0
max_slew_a_per_s = 10.0
compliance_v = 20.0
nominal_k_ut_per_a = [[40.0, 0.0, 0.0], [0.0, 40.0, 0.0], [0.0, 0.0, 40.0]]
""" + "".join(
    f'\n[devices.{n}]\nkind = "riden-rd60xx"\nprotocol = "modbus-tcp"\nhost = "127.0.0.1"\nport = {9 + i}\n'
    for i, n in enumerate(("coil_x", "coil_y", "coil_z"))
)


def check(tmp_path: Path, rig: str) -> int:
    proc, cfg = tmp_path / "p.yaml", tmp_path / "rig.toml"
    proc.write_text(PROC)
    cfg.write_text(rig)
    return main(["check", str(proc), "--rig", str(cfg)])


def warnings(out: str) -> list[str]:
    return [ln.removeprefix("WARNING: ") for ln in out.splitlines() if ln.startswith("WARNING: ")]


def test_configured_levels_above_the_limits_are_named_without_opening_anything(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rig = RIG.replace('port = 9\n', 'port = 9\nocp_a = 3.0\novp_v = 20.0\n') + (
        '\n[devices.load_bus]\nkind = "regmap-supply"\nregmap = "dps5005"\nprotocol = "modbus-tcp"'
        '\nhost = "127.0.0.1"\nport = 12\nmax_current_a = 1.0\ncompliance_v = 12.0'
        '\nmax_power_w = 10.0\novp_v = 13.0\nocp_a = 1.0\nopp_w = 30.0\n')  # fmt: skip
    code = check(tmp_path, rig)
    found = warnings(capsys.readouterr().out)
    assert code == 0  # warnings: the plan itself is within the limits
    assert found == [
        "coil_x: OCP is 3 A (ocp_a in [devices.coil_x]), above 2.5 A, the cage's max_current_a"
        " for axis x: the instrument would let the output pass the rig's limit before it switches"
        " off; lower it to at most 2.5 A (ocp_a = 2.5 in [devices.coil_x] is written when the rig"
        " opens it, or set it on the instrument)",
        "load_bus: OVP is 13 V (ovp_v in [devices.load_bus]), above 12 V, compliance_v of"
        " [devices.load_bus]: the instrument would let the output pass the rig's limit before it"
        " switches off; lower it to at most 12 V (ovp_v = 12 in [devices.load_bus] is written"
        " when the rig opens it, or set it on the instrument)",
        "load_bus: OPP is 30 W (opp_w in [devices.load_bus]), above 10 W, max_power_w of"
        " [devices.load_bus]: the instrument would let the output pass the rig's limit before it"
        " switches off; lower it to at most 10 W (opp_w = 10 in [devices.load_bus] is written"
        " when the rig opens it, or set it on the instrument)",
    ]  # ovp_v 20 V on coil_x is the cage's compliance_v itself, ocp_a 1 A the load's limit


@pytest.fixture(scope="module")
def sim_rig(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[SimulatedCage, Path]]:
    tmp = tmp_path_factory.mktemp("protections")
    swap = {"load_bus": 'kind = "regmap"\nregmap = "dps5005"\nbaudrate = 9600'}
    with cage_with(tmp, swap) as cage:
        doc = cage.endpoints_document()
        doc["devices"]["load_bus"]["regmap"] = "dps5005"
        text = rig_toml(doc, [[40.0, 0, 0], [0, 40.0, 0], [0, 0, 40.0]])
        text = text.replace("[devices.load_bus]\n", "[devices.load_bus]\nmax_current_a = 1.0\n")
        (tmp / "rig.toml").write_text(text)
        yield cage, tmp


def test_the_instruments_levels_are_read_and_the_configured_ones_written_at_open(
    sim_rig: tuple[SimulatedCage, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    _, tmp = sim_rig
    (tmp / "p.yaml").write_text(PROC)
    args = ["check", str(tmp / "p.yaml"), "--rig", str(tmp / "rig.toml"), "--protections", "-q"]
    assert main(args) == 0
    found = warnings(capsys.readouterr().out)
    # the Riden's power-on M0 OVP 62 V and OCP 6.2 A, the DPS5005's S-OVP 55 V and S-OCP 5.5 A
    assert [w.split(":")[0] for w in found] == [
        "coil_x", "coil_x", "coil_y", "coil_y", "coil_z", "coil_z", "trim_x", "trim_x", "trim_y",
        "trim_y", "trim_z", "trim_z", "load_bus", "load_bus", "heater", "heater"]  # fmt: skip
    assert found[0].startswith("coil_x: OVP is 62 V (register 82 (M0 OVP)), above 12 V, the"
                               " cage's compliance_v: ")  # fmt: skip
    assert found[1].startswith("coil_x: OCP is 6.2 A (register 83 (M0 OCP)), above 2.5 A, the"
                               " cage's max_current_a for axis x: ")  # fmt: skip
    assert found[12].startswith("load_bus: OVP is 55 V (register 's_ovp' (0x0052)), above 12 V,"
                                " compliance_v of [devices.load_bus]: ")  # fmt: skip
    assert found[13].startswith("load_bus: OCP is 5.5 A (register 's_ocp' (0x0053)), above 1 A,"
                                " max_current_a of [devices.load_bus]: ")  # fmt: skip
    # the rig file sets the DPS's levels: written (and read back) when the rig opens it as a load
    text = (tmp / "rig.toml").read_text()
    (tmp / "rig.toml").write_text(text.replace(
        "[devices.load_bus]\n", "[devices.load_bus]\novp_v = 12.0\nocp_a = 1.0\n"))  # fmt: skip
    cfg = load_rig_config(tmp / "rig.toml")
    with ExitStack() as stack:
        load = open_load(cfg.devices["load_bus"], None, cfg)
        stack.callback(load.close)
        stack.callback(load.safe)
    assert main(args) == 0
    after = warnings(capsys.readouterr().out)
    assert [w for w in after if w.startswith("load_bus")] == []
    assert len(after) == len(found) - 2


def test_an_instrument_that_does_not_answer_leaves_the_levels_not_checked(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    proc, cfg = tmp_path / "p.yaml", tmp_path / "rig.toml"
    proc.write_text(PROC)
    cfg.write_text(RIG.replace("port = 9\n", "port = 9\ntimeout_s = 0.2\n"))
    assert main(["check", str(proc), "--rig", str(cfg), "--protections", "-q"]) == 1
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("NOT CHECKED")]
    assert len(lines) == 3
    assert lines[0].startswith("NOT CHECKED: coil_x: its protection levels were not read (")
