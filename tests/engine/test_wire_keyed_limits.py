"""Limits bound to the wire, and one pre-run check (issue 51): the same supply as ``coil_x``
declared a second time under another name (its host spelled ``localhost``) and used as a load at
4-6 A took coil_x to 3.0 A against 2.5 A, |B| to 140 uT against 120 uT. Now `rig check` and `rig
run` refuse the configuration before anything is locked or written; forced past that, the second
name has coil_x's limits. And `rig run` refuses, before the lock or any output, what `rig check
--rig` refuses (a 110 uT field on z needs 2.68 A of a 2.5 A axis: the run used to hold a null for
17 s first; and with the lab field not yet measured it may reach 176 uT)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from rig.config import load_rig_config
from rig.engine.interlock import RigLock
from rig.engine.runner import Runner
from rig.errors import UserInputError
from rig.output_limits import cage_role, output_limits
from rig.procedure.language import parse_procedure
from rig.wire_address import same_device, shared_addresses
from sim.cage import SimulatedCage

RIG = [sys.executable, "-m", "rig.cli"]
AUX_AS_LOAD = """procedure: A second name for coil_x
magnetometers: {dut: dut, reference: reference}
loads: [aux]
steps:
  - set_field: {field_ut: [0, 0, 0], hold_s: 2}
    loads:
      aux: {ramp: {from_a: 4.0, to_a: 6.0, step_s: 0.1}}
"""
Z_110 = """procedure: Beyond the z axis
magnetometers: {dut: dut, reference: reference}
steps:
  - set_field: {field_ut: [0, 0, 110], hold_s: 2}
"""

pytestmark = [pytest.mark.realtime, pytest.mark.usefixtures("own_lock_dir")]


def with_aux(rig_toml: Path, host: str = "localhost") -> Path:
    """The rig file with ``[devices.aux]``: coil_x's kind, port and id, its host spelled
    ``host``."""
    text = rig_toml.read_text()
    block = re.search(r"\[devices\.coil_x\]\n(.*?)\n\n", text, re.S)
    assert block is not None
    aux = block.group(1).replace('host = "127.0.0.1"', f'host = "{host}"')
    out = rig_toml.with_name("aux-rig.toml")
    out.write_text(text + f"\n[devices.aux]\n{aux}\n")
    return out


def supply_writes(cage: SimulatedCage) -> dict[str, int]:
    return {n: s.writes for n, s in cage.physics.supplies.items()}


@pytest.mark.parametrize("host", ["localhost", "127.0.0.1"])
def test_one_instrument_under_two_names_is_found(rig_toml: Path, host: str) -> None:
    cfg = load_rig_config(with_aux(rig_toml, host))
    assert same_device(cfg, "aux", "coil_x") and not same_device(cfg, "aux", "coil_z")
    problems = shared_addresses(cfg)
    assert len(problems) == 1, problems
    assert (
        "[devices.coil_x] and [devices.aux] are one instrument (modbus-tcp 127.0.0.1:"
        in problems[0]
    )
    assert cage_role(cfg, "aux") == "the cage's x coil supply (coil_x, on the same address)"


def test_a_second_name_has_the_coils_limits(rig_toml: Path) -> None:
    """Past every refusal, the output opened as ``aux`` is held by the cage's limits for axis x
    (2.5 A, 12 V), not its instrument's 6 A range."""
    cfg = load_rig_config(with_aux(rig_toml))
    driver = SimpleNamespace(max_current_a=6.0, max_voltage_v=60.0)
    limits = output_limits(cfg, cfg.devices["aux"], driver)
    assert limits.max_current_a <= 2.5 and limits.max_voltage_v == 12.0, limits
    assert "axis x" in limits.current_from
    alone = output_limits(cfg, cfg.devices["load_bus"], driver)
    assert alone.max_current_a == 6.0, alone


def test_rig_check_refuses_the_second_name(rig_toml: Path, tmp_path: Path) -> None:
    proc = tmp_path / "p.yaml"
    proc.write_text(AUX_AS_LOAD)
    done = subprocess.run([*RIG, "check", str(proc), "--rig", str(with_aux(rig_toml))],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert done.returncode == 2, done
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr
    assert "[devices.coil_x] and [devices.aux] are one instrument" in lines[0], lines[0]
    assert "keep one table for it" in lines[0]


def test_rig_run_refuses_it_before_the_lock_or_any_write(
    cage: SimulatedCage, rig_toml: Path, tmp_path: Path
) -> None:
    proc = tmp_path / "p.yaml"
    proc.write_text(AUX_AS_LOAD)
    before, runs = supply_writes(cage), tmp_path / "runs"
    done = subprocess.run([*RIG, "run", str(proc), "--rig", str(with_aux(rig_toml)), "--yes",
                           "--runs-dir", str(runs)], capture_output=True, text=True, timeout=60)  # fmt: skip
    assert done.returncode == 2, done
    assert "are one instrument" in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert not runs.exists()
    assert supply_writes(cage) == before


def test_the_interlock_refuses_it_for_every_command(rig_toml: Path) -> None:
    """``rig cage ...`` and every other command that drives outputs takes the interlock first."""
    with pytest.raises(UserInputError, match="are one instrument"):
        RigLock(load_rig_config(with_aux(rig_toml)), "test").acquire()


def test_rig_run_refuses_what_rig_check_refuses(
    cage: SimulatedCage, rig_toml: Path, tmp_path: Path
) -> None:
    proc = tmp_path / "z.yaml"
    proc.write_text(Z_110)
    check = subprocess.run([*RIG, "check", str(proc), "--rig", str(rig_toml)],
                           capture_output=True, text=True, timeout=60)  # fmt: skip
    assert check.returncode == 1, check
    limits = [line for line in check.stdout.splitlines() if line.startswith("LIMIT: ")]
    assert any("needs +2.6" in ln and "on axis z" in ln and "beyond 2.5 A" in ln for ln in limits)
    limit = limits[0]  # the run names the first (here: the lab field not yet measured)
    before, runs = supply_writes(cage), tmp_path / "runs"
    runner = Runner(parse_procedure(proc), load_rig_config(rig_toml), runs, i2c_bus=cage.i2c_bus,
                    confirm=lambda s: True, live=False)  # fmt: skip
    with pytest.raises(UserInputError) as refused:
        runner.run()
    assert limit[len("LIMIT: ") :] in str(refused.value), (limit, refused.value)
    assert "nothing was switched on" in str(refused.value)
    assert not runs.exists()
    assert supply_writes(cage) == before
