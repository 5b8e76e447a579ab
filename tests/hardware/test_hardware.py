"""Tests on real hardware; they skip unless ``pytest --rig-config FILE`` names a rig configuration.

They only identify each device and put every output in its safe state: nothing here energizes a
coil, so they are safe to run on any bench.
"""

from __future__ import annotations

from contextlib import ExitStack

import pytest

from rig.config import RigConfig, load_rig_config
from rig.devices import open_device


@pytest.fixture(scope="module")
def rig_config(request: pytest.FixtureRequest) -> RigConfig:
    path = request.config.getoption("--rig-config")
    if not path:
        pytest.skip("hardware tests need --rig-config FILE")
    return load_rig_config(path)


def test_every_device_identifies_and_goes_safe(rig_config: RigConfig) -> None:
    with ExitStack() as stack:
        for name, dev in rig_config.devices.items():
            if dev.get("bus") == "sim":
                continue
            driver = open_device(dev)
            stack.callback(driver.close)
            if hasattr(driver, "safe"):
                stack.callback(driver.safe)
            ident = driver.identify()
            assert ident.model, f"{name}: empty identity"


def test_supplies_report_output_off_after_safe(rig_config: RigConfig) -> None:
    for dev in rig_config.devices.values():
        if dev.kind in ("riden-rd60xx", "regmap-supply", "regmap-eload"):
            supply = open_device(dev)
            try:
                supply.safe()
                assert not supply.read().output_on
            finally:
                supply.close()
