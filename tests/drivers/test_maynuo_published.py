"""The Maynuo M97/M98 driver and ``rig devices scan`` against register images typed in from the
makers' and an instrument library's tables, never from the simulator (regmaps/maynuo-m97.toml
names the sources):

* model codes: 101 = M9812 (libsigrok's maynuo-m97 model table, the one code it enables), 28 =
  M9710 (a user's unit, "Maynuo M9710 v3.2", libsigrok pull request #273);
* registers: CMD 0x0A00 (1 CC, 2 CV, 3 CW, 4 CR, 42 input on, 43 off), IFIX 0x0A01 float32 high
  word first, U/I 0x0B00/0x0B02, SETMODE 0x0B04 (the mode in its low byte: 0xFF01 in CC, 0xFF02
  in CV as David Ogilvy's client read a unit), MODEL 0x0B06, EDITION 0x0B07 (32 = v3.2);
  coils PC1 0x0500 (remote) and ISTATE 0x0510 (input on); functions 01, 03, 05 and 16 only.

Each load is found by the scan on a Modbus RTU line (a pseudo-terminal at 9600 Bd), then driven
in constant current: remote control first, CMD 1 and a read of SETMODE before the input is
switched on, never function 06. A code the map does not list is accepted with a warning naming
it; a load that does not take CC (a program running on its panel) is never switched on."""

from __future__ import annotations

import struct

import pytest

from drivers.errors import DeviceStateError
from drivers.registry import KINDS, Found, OpenSpec
from rig.bringup import scan, table
from tests.drivers.register_image import RegisterImage

CMD, IFIX, U, I_MEAS, SETMODE, MODEL, EDITION = (
    0x0A00,
    0x0A01,
    0x0B00,
    0x0B02,
    0x0B04,
    0x0B06,
    0x0B07,
)
PC1, ISTATE = 0x0500, 0x0510
MODES = {1: "CC", 2: "CV", 3: "CW", 4: "CR"}
PUBLISHED = [  # (model code, EDITION, the name the rig reports)
    (101, 0, "Maynuo M9812"),  # libsigrok's table; its version is not published (0 here)
    (28, 32, "Maynuo M9710"),  # libsigrok PR #273: "Maynuo M9710 v3.2"
]


def float_words(value: float) -> tuple[int, int]:
    """A float32 as two registers, high word first."""
    high, low = struct.unpack(">HH", struct.pack(">f", value))
    return high, low


def m97(code: int, edition: int, *, takes_modes: bool = True) -> RegisterImage:
    """An M97 load on its front panel in CV, input off, local control. CMD 1-4 set SETMODE's low
    byte (unless ``takes_modes`` is false: a program on its panel holds it in list mode 27);
    42/43 switch the input and its ISTATE coil; the current reads back IFIX while the input is on
    in CC."""
    regs = {a: 0 for a in range(CMD, CMD + 9)} | {a: 0 for a in range(U, EDITION + 1)}
    regs.update({SETMODE: 0xFF02 if takes_modes else 0xFF1B, MODEL: code, EDITION: edition})
    image = RegisterImage(regs, coils={PC1: False, ISTATE: False})

    def on_write(address: int, value: int) -> None:
        r, coils = image.regs, image.coils
        if address == CMD and value in MODES and takes_modes:
            r[SETMODE] = 0xFF00 | value
        elif address == CMD and value in (42, 43):
            coils[ISTATE] = value == 42
        in_cc = coils[ISTATE] and r[SETMODE] & 0xFF == 1
        r[I_MEAS], r[I_MEAS + 1] = (r[IFIX], r[IFIX + 1]) if in_cc else (0, 0)

    image.on_write = on_write
    return image


def scanned(image: RegisterImage, *, rtu: bool) -> tuple[list[Found], str]:
    if rtu:
        found, unknown = scan([image.serve_rtu()], [], [], timeout_s=0.2)
    else:
        found, unknown = scan([], [], [("127.0.0.1", image.port)], timeout_s=0.5)
    assert unknown == []
    return found, table(found, unknown)


@pytest.mark.parametrize(("code", "edition", "name"), PUBLISHED, ids=["M9812", "M9710"])
def test_scanned_on_rtu_then_driven_in_cc_the_input_on_only_after_cc_read_back(
    code: int, edition: int, name: str
) -> None:
    with m97(code, edition) as image:
        (found,), text = scanned(image, rtu=True)
        assert (found.kind, found.model, found.warning) == ("regmap-eload", name, "")
        assert found.params["regmap"] == "maynuo-m97" and found.params["baudrate"] == 9600
        assert name in text and "WARNING" not in text
        image.requests.clear()
        params = found.params | {"max_current_a": 5.0, "timeout_s": 1.0}
        load = KINDS["regmap-eload"].open(OpenSpec("load_panel", "modbus-rtu", params))
        try:
            load.enable_as_load(12.0)
            load.set_current(1.5)
            reading = load.read()
            load.safe()
        finally:
            load.close()
    log = image.requests
    assert log[:2] == [(5, PC1, (0xFF00,)), (1, PC1, (1,))]  # remote first, read back
    cc, on = log.index((16, CMD, (1,))), log.index((16, CMD, (42,)))
    assert cc < on and (3, SETMODE, (1,)) in log[cc + 1 : on]  # CC read back before the input
    assert (3, SETMODE, (1,)) in log[on + 1 :]  # and again once it is on
    assert (16, IFIX, float_words(1.5)) in log[on:]
    assert not [r for r in log if r[0] == 6]  # the M97 has no function 06
    assert reading.constant_current and reading.output_on and reading.i_out_a == 1.5
    assert log[-1] == (5, PC1, (0x0000,))  # local control again on close
    assert image.coils == {PC1: False, ISTATE: False}
    assert image.regs[CMD] == 43 and (image.regs[IFIX], image.regs[IFIX + 1]) == (0, 0)


def test_a_model_code_the_map_does_not_list_is_accepted_with_a_warning_naming_it() -> None:
    """53: libsigrok's guess for the M9711, "only guessed and needs to be verified"."""
    with m97(53, 0) as image:
        (found,), text = scanned(image, rtu=False)
        assert (found.kind, found.model) == ("regmap-eload", "Maynuo M97/M98 (model code 53)")
        assert "reads 53, a model code the map maynuo-m97 does not list" in found.warning
        assert "101 = Maynuo M9812, 28 = Maynuo M9710" in found.warning
        warning = next(ln for ln in text.splitlines() if ln.startswith("WARNING"))
        assert f"127.0.0.1:{image.port}" in warning and "53" in warning
        load = KINDS["regmap-eload"].open(OpenSpec("load", "modbus-tcp", found.params))
        try:
            ident = load.identify()
        finally:
            load.close()
        assert ident.model == found.model and ident.warning == found.warning


def test_a_load_that_does_not_take_constant_current_is_never_switched_on() -> None:
    with m97(101, 0, takes_modes=False) as image:
        spec = OpenSpec("load_panel", "modbus-tcp",
                        {"host": "127.0.0.1", "port": image.port, "regmap": "maynuo-m97"})  # fmt: skip
        load = KINDS["regmap-eload"].open(spec)
        try:
            with pytest.raises(DeviceStateError) as info:
                load.enable_as_load(12.0)
        finally:
            load.close()
    message = str(info.value)
    assert "\n" not in message and message.startswith("load_panel at 127.0.0.1:")
    assert "does not read back constant current before its input is switched on" in message
    assert "reads 0xff1b, CC reads 1 under mask 0x00ff" in message
    assert "take it out of any program on its front panel" in message
    assert (16, CMD, (1,)) in image.requests and (16, CMD, (42,)) not in image.requests
    assert not image.coils[ISTATE]
