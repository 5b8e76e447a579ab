"""Instrument drivers: wire protocols of magnetometers and supplies. Imports neither rig nor sim."""
