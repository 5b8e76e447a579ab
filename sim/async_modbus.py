"""The Modbus devices on the wall clock: pymodbus 3.16 asyncio servers on one event loop in a
background thread, behind fault-injecting loopback TCP proxies or pty null modems
(:mod:`sim.transports`). In simulated time :mod:`sim.pipe_modbus` serves them instead."""

from __future__ import annotations

import asyncio
import contextlib
from concurrent.futures import Future
from typing import Any

from pymodbus import FramerType
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import SimDevice

import timebase
from sim.modbus_requests import QUANTITY_CHECKED
from sim.physics import Faults
from sim.transports import PtyNullModem, TcpProxy


class AsyncioModbus:
    """Modbus servers on an asyncio loop of their own (``seed``: the links' fault draws)."""

    def __init__(self, seed: int) -> None:
        self.seed = seed
        self._loop = asyncio.new_event_loop()
        self._thread = timebase.Thread(self._loop.run_forever, name="sim-modbus", daemon=True)
        self._thread.start()
        self._servers: list[Any] = []
        self._proxies: dict[str, TcpProxy] = {}
        self._modems: list[PtyNullModem] = []

    def _run(self, coro: Any) -> Any:
        fut: Future[Any] = asyncio.run_coroutine_threadsafe(coro, self._loop)
        return fut.result(timeout=10.0)

    def serve_tcp(self, name: str, devices: list[SimDevice], faults: Faults) -> int:
        """Serve ``devices`` (one endpoint) on loopback TCP behind a proxy; returns its port."""

        async def start_tcp() -> ModbusTcpServer:
            srv = ModbusTcpServer(devices, address=("127.0.0.1", 0), custom_pdu=QUANTITY_CHECKED)
            await srv.serve_forever(background=True)
            return srv

        server = self._run(start_tcp())
        self._servers.append(server)
        backend = int(server.transport.sockets[0].getsockname()[1])
        proxy = TcpProxy(backend, faults, seed=self.seed)
        port = int(self._run(proxy.start()))
        self._proxies[name] = proxy
        return port

    def serve_rtu(self, name: str, device: SimDevice, device_id: int, baudrate: int,
                  faults: Faults) -> str:  # fmt: skip
        """Serve ``device`` as Modbus RTU behind a pty null modem; returns the client's path."""
        modem = PtyNullModem(faults, self._loop, device_id=device_id, seed=self.seed)
        self._modems.append(modem)

        async def start_rtu() -> ModbusSerialServer:
            srv = ModbusSerialServer(device, framer=FramerType.RTU, port=modem.device_path,
                                     baudrate=baudrate, custom_pdu=QUANTITY_CHECKED)  # fmt: skip
            await srv.serve_forever(background=True)
            return srv

        self._servers.append(self._run(start_rtu()))
        return modem.client_path

    def drop_connections(self, name: str) -> None:
        """Close the TCP connections of device ``name`` now."""
        proxy = self._proxies[name]
        self._loop.call_soon_threadsafe(proxy.drop_connections)

    def stop(self) -> None:
        """Stop every server, proxy and modem, then the loop."""
        if self._loop.is_running():
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
        if not self._loop.is_running() and not self._loop.is_closed():
            self._loop.close()  # its self-pipe's sockets too (else ResourceWarnings when collected)
        for modem in self._modems:
            modem.close()
        self._servers.clear()
        self._proxies.clear()
        self._modems.clear()
