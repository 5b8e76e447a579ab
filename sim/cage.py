"""The whole simulated cage: physics plus every device on its real transport.

    cage = SimulatedCage(load_config())
    endpoints = cage.start()   # {"devices": {name: {"kind", "protocol", "host", "port", ...}}}
    ...
    cage.stop()

Modbus devices run on one asyncio loop in a background thread (pymodbus 3.16 servers behind
fault-injecting TCP proxies or pty null modems); serial magnetometers run their own threads on
ptys; the RM3100 sits on an in-process smbus2-compatible bus (``cage.i2c_bus``).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from concurrent.futures import Future
from typing import Any

from pymodbus import FramerType
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import SimDevice

from sim.ascii_mag import AsciiMagnetometer
from sim.config import EndpointConfig, SimConfig
from sim.hmr2300 import Hmr2300
from sim.links import PtyNullModem, TcpProxy
from sim.modbus_devices import regmap_device, riden_device, unserved_ids
from sim.physics import CagePhysics, Faults
from sim.regmap import load_regmap
from sim.rm3100 import Rm3100, SimI2CBus

KIND_BY_SUPPLY = {"riden-rd60xx": "riden-rd60xx", "regmap": "regmap"}


class SimulatedCage:
    """Start and stop the simulated cage; ``faults[name]`` injects faults per device."""

    def __init__(self, cfg: SimConfig) -> None:
        self.cfg = cfg
        self.physics = CagePhysics(cfg)
        self.faults: dict[str, Faults] = {}
        self.endpoints: dict[str, dict[str, Any]] = {}
        self.i2c_bus = SimI2CBus()
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(
            target=self._loop.run_forever, name="sim-modbus", daemon=True
        )
        self._servers: list[Any] = []
        self._proxies: dict[str, TcpProxy] = {}
        self._modems: list[PtyNullModem] = []
        self._serial_devices: list[Hmr2300 | AsciiMagnetometer] = []
        self.serial_devices: dict[str, Hmr2300 | AsciiMagnetometer] = {}
        self.i2c_devices: dict[str, Rm3100] = {}
        self._started = False

    def _run(self, coro: Any) -> Any:
        fut: Future[Any] = asyncio.run_coroutine_threadsafe(coro, self._loop)
        return fut.result(timeout=10.0)

    def start(self) -> dict[str, Any]:
        """Start every device; returns the endpoints document (see :meth:`endpoints_document`)."""
        if self._started:
            return self.endpoints_document()
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
        self._thread.start()
        self._started = True
        try:
            for s in self.cfg.supplies:
                supply = self.physics.supplies[s.name]
                self.faults[s.name] = supply.faults
                if s.kind == "riden-rd60xx":
                    device = riden_device(supply, s.endpoint.device_id)
                    kind = "riden-rd60xx"
                else:
                    spec = load_regmap(s.regmap)
                    if spec.kind == "eload":
                        supply.set_voltage(min(s.input_voltage_v, supply.v_max))
                    device = regmap_device(
                        spec, s.endpoint.device_id, self.physics, supply, supply.faults
                    )
                    kind = f"regmap-{spec.kind}"
                entry = self._serve_modbus(s.name, device, s.endpoint.transport,
                                           s.endpoint.device_id, s.endpoint.baudrate, supply.faults)  # fmt: skip
                entry["kind"] = kind
                if s.kind == "regmap":
                    entry["regmap"] = load_regmap(s.regmap).source
                entry["role"] = f"coil_{'xyz'[s.axis]}" if s.axis is not None else "load"
                self.endpoints[s.name] = entry
            if self.cfg.relay is not None:
                r = self.cfg.relay
                self._serve_map_device(r.name, r.regmap, r.endpoint, self.physics.relays.faults,
                                       "regmap-relay", "polarity")  # fmt: skip
            if self.cfg.thermometer is not None:
                th = self.cfg.thermometer
                self._serve_map_device(th.name, th.regmap, th.endpoint, Faults(),
                                       "regmap-thermometer", "thermometer")  # fmt: skip
            for i, m in enumerate(self.cfg.magnetometers):
                mag = self.physics.magnetometers[m.name]
                self.faults[m.name] = mag.faults

                def reader(t_s: float, name: str = m.name) -> Any:
                    return self.physics.read_magnetometer(name, t_s)

                if m.kind == "hmr2300":
                    dev = Hmr2300(reader, mag.faults, device_id=m.endpoint.device_id,
                                  baudrate=m.endpoint.baudrate, serial_number=m.serial_number,
                                  seed=self.cfg.seed + i)  # fmt: skip
                    self._serial_devices.append(dev)
                    self.serial_devices[m.name] = dev
                    self.endpoints[m.name] = {"kind": "hmr2300", "protocol": "serial",
                                              "path": dev.path, "baudrate": m.endpoint.baudrate,
                                              "device_id": m.endpoint.device_id}  # fmt: skip
                elif m.kind == "ascii-mag":
                    adev = AsciiMagnetometer(reader, mag.faults, rate_hz=m.rate_hz,
                                             baudrate=m.endpoint.baudrate,
                                             line_format=m.line_format, seed=self.cfg.seed + i)  # fmt: skip
                    self._serial_devices.append(adev)
                    self.serial_devices[m.name] = adev
                    self.endpoints[m.name] = {"kind": "ascii-mag", "protocol": "serial",
                                              "path": adev.path, "baudrate": m.endpoint.baudrate,
                                              "line_format": m.line_format, "unit": "uT"}  # fmt: skip
                elif m.kind == "rm3100":
                    rdev = Rm3100(reader, mag.faults, m.i2c_address)
                    self.i2c_bus.attach(rdev)
                    self.i2c_devices[m.name] = rdev
                    self.endpoints[m.name] = {"kind": "rm3100", "protocol": "i2c",
                                              "bus": "sim", "address": m.i2c_address}  # fmt: skip
                else:
                    raise ValueError(f"magnetometer '{m.name}': unknown kind '{m.kind}'")
            for name, settings in self.cfg.faults.items():
                for key, value in settings.items():
                    setattr(self.faults[name], key, value)
        except BaseException:
            self.stop()
            raise
        return self.endpoints_document()

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
        if transport == "modbus-tcp":
            # unit ids other than the device's get exception 11, as from a gateway (id 0: the
            # device itself is pymodbus' catch-all and answers every id, as some devices do)
            devices = [device] if device_id == 0 else [device, unserved_ids()]

            async def start_tcp() -> ModbusTcpServer:
                srv = ModbusTcpServer(devices, address=("127.0.0.1", 0))
                await srv.serve_forever(background=True)
                return srv

            server = self._run(start_tcp())
            self._servers.append(server)
            backend = int(server.transport.sockets[0].getsockname()[1])
            proxy = TcpProxy(backend, faults, seed=self.cfg.seed)
            port = self._run(proxy.start())
            self._proxies[name] = proxy
            return {"protocol": "modbus-tcp", "host": "127.0.0.1", "port": port,
                    "device_id": device_id}  # fmt: skip
        if transport == "modbus-rtu":
            modem = PtyNullModem(faults, self._loop, device_id=device_id, seed=self.cfg.seed)
            self._modems.append(modem)

            async def start_rtu() -> ModbusSerialServer:
                srv = ModbusSerialServer(device, framer=FramerType.RTU, port=modem.device_path,
                                         baudrate=baudrate)  # fmt: skip
                await srv.serve_forever(background=True)
                return srv

            self._servers.append(self._run(start_rtu()))
            return {"protocol": "modbus-rtu", "path": modem.client_path, "baudrate": baudrate,
                    "device_id": device_id, "parity": "N", "stopbits": 1}  # fmt: skip
        raise ValueError(f"device '{name}': transport '{transport}' is not a Modbus transport")

    def drop_connections(self, name: str) -> None:
        """Fault on demand: close the TCP connections of a Modbus device now."""
        proxy = self._proxies[name]
        self._loop.call_soon_threadsafe(proxy.drop_connections)

    def endpoints_document(self) -> dict[str, Any]:
        """The endpoints contract: ``{"devices": {name: {...}}}``."""
        return {"devices": {k: dict(v) for k, v in self.endpoints.items()}}

    def stop(self) -> None:
        """Stop every server and thread; outputs are switched off first."""
        with contextlib.suppress(Exception):
            self.physics.safe()
        for dev in self._serial_devices:
            dev.close()
        if self._started and self._loop.is_running():
            for proxy in self._proxies.values():
                with contextlib.suppress(Exception):
                    self._run(proxy.stop())
            for server in self._servers:
                with contextlib.suppress(Exception):
                    self._run(server.shutdown())
            for modem in self._modems:  # detached from the loop while it runs
                modem.close()
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=5.0)
        for modem in self._modems:
            modem.close()
        self._servers.clear()
        self._proxies.clear()
        self._modems.clear()
        self._serial_devices.clear()
        self._started = False

    def __enter__(self) -> SimulatedCage:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
