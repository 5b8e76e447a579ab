"""Supplies, electronic loads and polarity relays over Modbus."""
