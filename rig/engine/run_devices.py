"""Opening a run's devices inside its ``RigSession``: a sampler per magnetometer, the procedure's
loads, every thermometer of the rig, and the instruments' identities for the record. Whatever is
started here stops through the session (``RigSession.on_close``): after its safe state, before
the links close."""

from __future__ import annotations

import contextlib
import datetime as dt
from collections.abc import Callable
from typing import Any

import timebase
from drivers.errors import DeviceError
from rig.cage_budget import certificate_of
from rig.config import RigConfig
from rig.devices import thermometer_names
from rig.engine.commands import LoadBook
from rig.engine.sampling import BufferedSensor, SensorSampler
from rig.engine.session import RigSession
from rig.engine.temperature_log import Interlock, TemperatureLog
from rig.errors import RigError
from rig.procedure.language import Procedure
from rig.steps import KINDS
from rig.store.instruments import instruments
from rig.store.run_store import RunWriter

Event = Callable[[str, str], None]


def _identity(device: Any, warn: Callable[[str], None] | None = None) -> str | None:
    """'model serial' of ``device``, None if it cannot say (an identity is for the record only);
    a caveat of its identification (a model code its map does not list) told to ``warn``."""
    with contextlib.suppress(Exception):
        ident = device.identify()
        if ident.warning and warn is not None:
            warn(ident.warning)
        return f"{ident.model} {ident.serial}".strip()
    return None


def start_samplers(rig: RigSession, proc: Procedure, cfg: RigConfig, writer: RunWriter,
                   samplers: dict[str, SensorSampler], instruments: dict[str, str],
                   event: Event) -> None:  # fmt: skip
    """One sampler per magnetometer device, whatever its roles, and the cage's ``ambient``
    magnetometer (outside the coils: recorded in every run), into ``samplers``; the cage's
    reference is read through its sampler."""
    for role, dev_name in proc.magnetometers.items():
        if dev_name not in cfg.devices:
            raise RigError(f"{proc.path}: magnetometer role '{role}' names '{dev_name}',"
                           f" which is not in {cfg.path}")  # fmt: skip
    cage_reference = cfg.cage.reference if cfg.cage is not None else None
    ambient = [cfg.cage.ambient] if cfg.cage is not None and cfg.cage.ambient else []
    for dev_name in dict.fromkeys([*proc.magnetometers.values(), *ambient]):
        driver = rig.magnetometer(dev_name)
        if (ident := _identity(driver)) is not None:
            instruments[dev_name] = ident
        rate = float(cfg.devices[dev_name].get("rate_hz", 20.0))
        sampler = SensorSampler(dev_name, driver, writer.add_sample, rate,
                                on_warning=lambda m: event("warning", m))  # fmt: skip
        sampler.start()
        rig.on_close(sampler.stop)
        samplers[dev_name] = sampler
        if dev_name == cage_reference:
            rig.cage().reference = BufferedSensor(sampler)


def open_loads(rig: RigSession, proc: Procedure, cfg: RigConfig, book: LoadBook,
               instruments: dict[str, str], event: Event | None = None) -> None:  # fmt: skip
    """The procedure's load channels, at 0 A with their outputs on (off when the session ends);
    a load identified with a caveat (an unlisted model code) is a ``warning`` event."""
    for name in proc.loads:
        if name not in cfg.devices:
            raise RigError(f"{proc.path}: load '{name}' is not a device in {cfg.path}")
        load = rig.load(name)
        book.loads[name] = load
        book.commanded[name] = 0.0

        def warn(message: str, name: str = name) -> None:
            if event is not None:
                event("warning", f"{name}: {message}")

        if (ident := _identity(load, warn)) is not None:
            instruments[name] = ident


def record_thermometers(rig: RigSession, cfg: RigConfig, writer: RunWriter,
                        instruments: dict[str, str], event: Event) -> list[str]:  # fmt: skip
    """Start recording every thermometer of the rig (channels in degrees C, one reading a
    second); one that cannot be opened is a warning, never the end of the run, unless it is the
    temperature interlock (``max_temperature_c``) of one of the run's loads (``heats``; ADR
    0035). Returns the names being recorded."""
    recorded = []
    for name in thermometer_names(cfg):
        lock = _interlock(rig, cfg, name)
        try:
            thermometer = rig.thermometer(name)
            if (ident := _identity(thermometer)) is not None:
                instruments[name] = ident
        except (DeviceError, OSError, RigError) as exc:
            if lock is not None and (heaters := _heaters(rig, cfg, name)):
                raise RigError(f"{exc}; {name} is the temperature interlock of"
                               f" {', '.join(heaters)} (max_temperature_c), so nothing is driven"
                               f" without it: check {name}'s link and wiring") from None  # fmt: skip
            event("warning", f"{exc}; the run goes on without recording {name}")
            continue
        log = TemperatureLog(name, thermometer, writer.add_channel, event, interlock=lock)
        log.start()
        rig.on_close(log.stop)
        recorded.append(name)
    return recorded


def _heaters(rig: RigSession, cfg: RigConfig, thermometer: str) -> list[str]:
    """The run's loads that warm ``thermometer`` (their ``heats``)."""
    return [n for n in list(rig.loads) if n in cfg.devices
            and cfg.devices[n].get("heats") == thermometer]  # fmt: skip


def _interlock(rig: RigSession, cfg: RigConfig, name: str) -> Interlock | None:
    """Thermometer ``name`` as the DUT's temperature interlock, if it has ``max_temperature_c``:
    the run fails beyond it, or when it goes silent while a load that heats it has a current
    set-point (ADR 0035)."""
    limit = cfg.devices[name].get("max_temperature_c")
    if limit is None:
        return None

    def heating() -> list[str]:
        return [n for n in _heaters(rig, cfg, name)
                if getattr(rig.loads[n], "current_set_a", 1.0) != 0.0]  # fmt: skip

    return Interlock(float(limit), rig.fail, heating)


def check_thermometers(proc: Procedure, cfg: RigConfig, recorded: list[str]) -> None:
    """Every thermometer a step reads is one this run records."""
    for step in proc.steps:
        for name in KINDS[step.kind].thermometers(step):
            if name not in recorded:
                raise RigError(
                    f"{proc.path}: step '{step.name}' reads thermometer '{name}', which"
                    f" this run does not record (recording: {', '.join(recorded) or 'none'});"
                    f" add it to {cfg.path} or fix the name"
                )


def reference_correction(proc: Procedure, cfg: RigConfig) -> dict[str, Any] | None:
    """The reference magnetometer's certificate and place (:func:`rig.cage_budget.certificate_of`),
    None without one."""
    return certificate_of(cfg, proc.magnetometers.get("reference"))


def warn_expired_certificates(cfg: RigConfig, event: Callable[[str, str], None]) -> None:
    """A warning in the run's log for every instrument whose calibration certificate
    (``certificate_expires`` in the rig configuration) has expired by today: the run goes on, and
    its report flags the certificate beside the verdict."""
    today = dt.datetime.fromtimestamp(timebase.wall_time(), dt.UTC).date().isoformat()
    for found in instruments(cfg.raw, today):
        if found.expired:
            event("warning", f"the calibration certificate of '{found.name}' (serial"
                  f" {found.serial or '-'}) expired on {found.certificate_expires}: renew it; this"
                  " run's report flags it")  # fmt: skip
