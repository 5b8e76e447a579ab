"""The two commercial "Modbus RTU relay" boards as polarity relays, byte for byte on a pty (9600 Bd),
with the frames their makers' documents and an independent client give (regmaps/waveshare-relay.toml
and regmaps/r421a08-relay.toml name them): every switch is read back, the safe state is every
relay off, and a relay that does not follow is an error before anything else is switched."""

from __future__ import annotations

import pytest

from drivers.errors import DeviceStateError
from drivers.psu.regmap_device import PolarityRelay
from drivers.transport.modbus import ModbusLink
from regmaps import load_map
from tests.drivers.scripted import Exchange, ScriptedSerialPeer, rtu


def relay(name: str, script: list[Exchange]) -> tuple[PolarityRelay, ScriptedSerialPeer]:
    peer = ScriptedSerialPeer(script)
    link = ModbusLink(name="polarity", path=peer.path, baudrate=9600, timeout_s=0.5, retries=0)
    return PolarityRelay(link, load_map(name)), peer


def test_the_frames_of_the_waveshare_manual_are_what_rtu_makes() -> None:
    """The Waveshare protocol manual's examples, CRC included, against this test's own CRC."""
    assert rtu("01 05 00 00 FF 00") == bytes.fromhex("01 05 00 00 FF 00 8C 3A")  # relay 0 on
    assert rtu("01 05 00 01 FF 00") == bytes.fromhex("01 05 00 01 FF 00 DD FA")  # relay 1 on
    assert rtu("01 05 00 01 00 00") == bytes.fromhex("01 05 00 01 00 00 9C 0A")  # relay 1 off


BOARDS = {
    # coils 0-2 by function 05 (0xFF00 on, 0x0000 off, echoed), read by function 01 (one bit)
    "waveshare-relay": (0, "01 05 00 {a:02X} FF 00", "01 05 00 {a:02X} 00 00",
                        "01 01 00 {a:02X} 00 01", "01 01 01 01", "01 01 01 00"),
    # registers 1-3 by function 06 (0x0100 on, 0x0200 off, echoed), read by function 03 (0/1)
    "r421a08-relay": (1, "01 06 00 {a:02X} 01 00", "01 06 00 {a:02X} 02 00",
                      "01 03 00 {a:02X} 00 01", "01 03 02 00 01", "01 03 02 00 00"),
}  # fmt: skip
"""Per board: the first relay's address, the frames to switch relay ``a`` on and off and to read
it, and the replies reading on and off (without CRC)."""


@pytest.mark.parametrize("name", list(BOARDS))
def test_a_polarity_switch_is_read_back_and_safe_is_every_relay_off(name: str) -> None:
    """Relay 2 (the y axis) reversed and read back, read again; then every relay off, each
    read back."""
    first, on, off, read, reads_on, reads_off = BOARDS[name]
    y = first + 1
    script = [Exchange(rtu(on.format(a=y)), rtu(on.format(a=y))),
              Exchange(rtu(read.format(a=y)), rtu(reads_on)),
              Exchange(rtu(read.format(a=y)), rtu(reads_on))]  # fmt: skip
    for a in range(first, first + 3):
        script += [Exchange(rtu(off.format(a=a)), rtu(off.format(a=a))),
                   Exchange(rtu(read.format(a=a)), rtu(reads_off))]  # fmt: skip
    board, peer = relay(name, script)
    try:
        board.set_polarity(1, -1)
        assert board.polarity(1) == -1
        board.safe()
    finally:
        board.close()
        peer.close()
    assert peer.mismatches == []


@pytest.mark.parametrize("name", list(BOARDS))
def test_a_relay_that_does_not_switch_is_an_error(name: str) -> None:
    first, on, _, read, _, reads_off = BOARDS[name]
    y = first + 1
    board, peer = relay(name, [Exchange(rtu(on.format(a=y)), rtu(on.format(a=y))),
                               Exchange(rtu(read.format(a=y)), rtu(reads_off))])  # fmt: skip
    try:
        with pytest.raises(DeviceStateError, match=r"polarity at /dev/pts/\d+: 'relay2' \(0x000"
                           r"\d\) reads off after being switched on; check the device's power"):  # fmt: skip
            board.set_polarity(1, -1)
    finally:
        board.close()
        peer.close()
    assert peer.mismatches == []
