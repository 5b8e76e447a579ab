"""Magnetometer drivers: HMR2300 (serial), RM3100 and LIS3MDL (I2C), configurable ASCII lines."""
