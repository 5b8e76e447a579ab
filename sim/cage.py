"""The whole simulated cage: physics plus every device on its real transport.

Each supply and magnetometer is started by its kind (:data:`sim.device_kinds.KINDS`, one module
per kind); the polarity relays and the DUT's thermometer are register-map devices served here.

    cage = SimulatedCage(load_config())
    endpoints = cage.start()   # {"devices": {name: {"kind", "protocol", "host", "port", ...}}}
    ...
    cage.stop()

On the wall clock, Modbus devices run on one asyncio loop in a background thread (pymodbus 3.16
servers behind fault-injecting TCP proxies or pty null modems, :mod:`sim.async_modbus`) and
serial magnetometers run their own threads on ptys. Started inside ``timebase.simulated()``
(ADR 0038), the cage runs entirely in simulated time: Modbus devices are served synchronously on
the clock's loopback network and serial lines (:mod:`sim.pipe_modbus`), serial magnetometers on
``simpipe://<name>`` lines (:mod:`sim.serial_line`), every thread a participant of the clock; the
endpoints document has the same shape. Stop such a cage before leaving the simulated block. The
RM3100 and LIS3MDL sit on an in-process smbus2-compatible bus (``cage.i2c_bus``) either way.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
from pymodbus.simulator import SimDevice

import timebase
from sim.config import EndpointConfig, SimConfig
from sim.device_kind import SerialDevice
from sim.device_kinds import sim_kind
from sim.i2c_bus import BusDevice, SimI2CBus
from sim.modbus_devices import regmap_device, unserved_ids
from sim.own_processor import instrument_priority
from sim.physics import CagePhysics, Faults
from sim.regmap import load_regmap


class ModbusHost(Protocol):
    """Where the cage's Modbus devices are served: :class:`sim.async_modbus.AsyncioModbus` (the
    wall clock) or :class:`sim.pipe_modbus.PipeModbus` (simulated time)."""

    def serve_tcp(self, name: str, devices: list[SimDevice], faults: Faults) -> int: ...

    def serve_rtu(self, name: str, device: SimDevice, device_id: int, baudrate: int,
                  faults: Faults) -> str: ...  # fmt: skip

    def drop_connections(self, name: str) -> None: ...

    def stop(self) -> None: ...


def modbus_host(seed: int) -> ModbusHost:
    """The Modbus servers for the current clock."""
    if timebase.is_simulated():
        from sim.pipe_modbus import PipeModbus

        return PipeModbus(seed)
    from sim.async_modbus import AsyncioModbus

    return AsyncioModbus(seed)


class SimulatedCage:
    """Start and stop the simulated cage; ``faults[name]`` injects faults per device."""

    def __init__(self, cfg: SimConfig) -> None:
        self.cfg = cfg
        self.physics = CagePhysics(cfg)
        self.faults: dict[str, Faults] = {}
        self.endpoints: dict[str, dict[str, Any]] = {}
        self.i2c_bus = SimI2CBus()
        self._modbus: ModbusHost | None = None
        self._serial_devices: list[SerialDevice] = []
        self.serial_devices: dict[str, Any] = {}  # name -> device (Hmr2300, AsciiMagnetometer)
        self.i2c_devices: dict[str, BusDevice] = {}
        self._started = False
        self.own_processor = False  # its threads run at a raised priority (see start)

    def start(self) -> dict[str, Any]:
        """Start every device; returns the endpoints document (see :meth:`endpoints_document`)."""
        if self._started:
            return self.endpoints_document()
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
        # the devices' threads start at an instrument's priority (sim.own_processor)
        with instrument_priority() as self.own_processor:
            self._start_devices()
        return self.endpoints_document()

    def _start_devices(self) -> None:
        self._modbus = modbus_host(self.cfg.seed)
        self._started = True
        try:
            for i, s in enumerate(self.cfg.supplies):
                self.faults[s.name] = self.physics.supplies[s.name].faults
                kind = sim_kind("supplies", s.kind, s.name)
                self.endpoints[s.name] = kind.start(self, s, i)
            if self.cfg.relay is not None:
                r = self.cfg.relay
                self._serve_map_device(r.name, r.regmap, r.endpoint, self.physics.relays.faults,
                                       "regmap-relay", "polarity")  # fmt: skip
            if self.cfg.thermometer is not None:
                th = self.cfg.thermometer
                self._serve_map_device(th.name, th.regmap, th.endpoint, Faults(),
                                       "regmap-thermometer", "thermometer")  # fmt: skip
            for i, m in enumerate(self.cfg.magnetometers):
                self.faults[m.name] = self.physics.magnetometers[m.name].faults
                kind = sim_kind("magnetometers", m.kind, m.name)
                self.endpoints[m.name] = kind.start(self, m, i)
            for name, settings in self.cfg.faults.items():
                for key, value in settings.items():
                    setattr(self.faults[name], key, value)
        except BaseException:
            self.stop()
            raise

    # --- what a device kind's start uses (sim.device_kind.CageHost) -----------------------------

    def serve_modbus(self, name: str, device: SimDevice, endpoint: EndpointConfig,
                     faults: Faults) -> dict[str, Any]:  # fmt: skip
        """Serve a Modbus device on its endpoint; returns the endpoint entry (no kind yet)."""
        return self._serve_modbus(name, device, endpoint.transport, endpoint.device_id,
                                  endpoint.baudrate, faults)  # fmt: skip

    def add_serial(self, name: str, device: SerialDevice) -> None:
        """Own a pseudo-terminal device (closed on stop)."""
        self._serial_devices.append(device)
        self.serial_devices[name] = device

    def add_i2c(self, name: str, device: BusDevice) -> None:
        """Put a device on the simulated I2C bus."""
        self.i2c_bus.attach(device)
        self.i2c_devices[name] = device

    def field_reader(self, name: str) -> Callable[[float], np.ndarray]:
        """``read(t_s)``: what magnetometer ``name`` senses (uT, its frame) at time ``t_s``."""

        def read(t_s: float) -> np.ndarray:
            return self.physics.read_magnetometer(name, t_s)

        return read

    def _serve_map_device(self, name: str, regmap: str, endpoint: EndpointConfig, faults: Faults,
                          kind: str, role: str) -> None:  # fmt: skip
        """Serve a register-map device bound to no supply (the polarity relays, the DUT's
        thermometer) and publish its endpoint as ``kind`` playing ``role``."""
        spec = load_regmap(regmap)
        self.faults[name] = faults
        device = regmap_device(spec, endpoint.device_id, self.physics, None, faults)
        entry = self._serve_modbus(name, device, endpoint.transport, endpoint.device_id,
                                   endpoint.baudrate, faults)  # fmt: skip
        self.endpoints[name] = entry | {"kind": kind, "regmap": spec.source, "role": role}

    def _serve_modbus(self, name: str, device: SimDevice, transport: str, device_id: int,
                      baudrate: int, faults: Faults) -> dict[str, Any]:  # fmt: skip
        if self._modbus is None:
            raise RuntimeError("start the cage before serving its devices")
        if transport == "modbus-tcp":
            # unit ids other than the device's get exception 11, as from a gateway (id 0: the
            # device itself is pymodbus' catch-all and answers every id, as some devices do)
            devices = [device] if device_id == 0 else [device, unserved_ids()]
            port = self._modbus.serve_tcp(name, devices, faults)
            return {"protocol": "modbus-tcp", "host": "127.0.0.1", "port": port,
                    "device_id": device_id}  # fmt: skip
        if transport == "modbus-rtu":
            path = self._modbus.serve_rtu(name, device, device_id, baudrate, faults)
            return {"protocol": "modbus-rtu", "path": path, "baudrate": baudrate,
                    "device_id": device_id, "parity": "N", "stopbits": 1}  # fmt: skip
        raise ValueError(f"device '{name}': transport '{transport}' is not a Modbus transport")

    def drop_connections(self, name: str) -> None:
        """Fault on demand: close the TCP connections of a Modbus device now."""
        if self._modbus is None:
            raise KeyError(name)
        self._modbus.drop_connections(name)

    def endpoints_document(self) -> dict[str, Any]:
        """The endpoints contract: ``{"devices": {name: {...}}}``."""
        return {"devices": {k: dict(v) for k, v in self.endpoints.items()}}

    def stop(self) -> None:
        """Stop every server and thread; outputs are switched off first."""
        with contextlib.suppress(Exception):
            self.physics.safe()
        for dev in self._serial_devices:
            dev.close()
        self._serial_devices.clear()  # closed once: a second stop must not close reused fds
        if self._modbus is not None:
            self._modbus.stop()
            self._modbus = None
        self._started = False

    def __enter__(self) -> SimulatedCage:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
