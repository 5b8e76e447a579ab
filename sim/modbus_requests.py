"""Requests whose quantity is out of the protocol's range, answered as the Modbus application
protocol says (V1.1b3, 6.1-6.4, 6.11, 6.17): exception 3 (illegal data value) under the
request's own function code, e.g. ``83 03`` for a read of 126 holding registers.

pymodbus 3.16 refuses such a request while decoding it (``verifyCount``), and both of its answer
paths (its server's handler, and :class:`sim.pipe_modbus.Answerer`) then reply ``80 01``: function
0, illegal function. The classes here take the quantity as it comes and refuse it when the request
is executed. Both servers of the simulator register them (pymodbus' ``custom_pdu``)."""

from __future__ import annotations

from typing import Any

from pymodbus.constants import ExcCodes
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.pdu.bit_message import (
    ReadCoilsRequest,
    ReadDiscreteInputsRequest,
    WriteMultipleCoilsRequest,
)
from pymodbus.pdu.register_message import (
    ReadHoldingRegistersRequest,
    ReadInputRegistersRequest,
    ReadWriteMultipleRegistersRequest,
)


class _QuantityChecked(ModbusPDU):
    """A request decoded whatever its quantity; one out of range answers exception 3."""

    quantity_out_of_range = False

    def decode(self, data: bytes) -> None:
        try:
            super().decode(data)
        except ValueError:  # pymodbus' verifyCount: the quantity, not the frame, is wrong
            self.quantity_out_of_range = True

    async def datastore_update(self, context: Any, device_id: int) -> ModbusPDU:
        if self.quantity_out_of_range:
            return ExceptionResponse(self.function_code, ExcCodes.ILLEGAL_VALUE)
        return await super().datastore_update(context, device_id)


class ReadCoils(_QuantityChecked, ReadCoilsRequest):
    """Function 1: 1-2000 coils."""


class ReadDiscreteInputs(_QuantityChecked, ReadDiscreteInputsRequest):
    """Function 2: 1-2000 inputs."""


class ReadHoldingRegisters(_QuantityChecked, ReadHoldingRegistersRequest):
    """Function 3: 1-125 registers."""


class ReadInputRegisters(_QuantityChecked, ReadInputRegistersRequest):
    """Function 4: 1-125 registers."""


class WriteMultipleCoils(_QuantityChecked, WriteMultipleCoilsRequest):
    """Function 15: 1-1968 coils (pymodbus checks 2000 while decoding, the rest when executing)."""


class ReadWriteMultipleRegisters(_QuantityChecked, ReadWriteMultipleRegistersRequest):
    """Function 23: 1-125 read, 1-121 written."""


QUANTITY_CHECKED: list[type[ModbusPDU]] = [
    ReadCoils,
    ReadDiscreteInputs,
    ReadHoldingRegisters,
    ReadInputRegisters,
    WriteMultipleCoils,
    ReadWriteMultipleRegisters,
]
"""The request classes a simulated Modbus server decodes with (``custom_pdu``)."""
