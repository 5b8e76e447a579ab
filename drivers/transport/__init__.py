"""Transports: serial by pyserial URL, Modbus (pymodbus, pinned), I2C (smbus2 or any i2c_rdwr)."""
