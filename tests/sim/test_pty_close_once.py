"""A simulated device's pty is closed once: closing it again (a second stop of the cage, a device
thread late to finish) must not close the pty a later simulator in the same process was given
with the same numbers. A Dask worker runs one simulated cage after another; once, under load, a
run lost its outside reference's stream this way (read failed: the device disconnected)."""

from __future__ import annotations

import os

import pytest

from sim.transports import open_pty

pytestmark = pytest.mark.realtime


def test_closing_twice_leaves_the_next_pty_with_the_same_numbers_open() -> None:
    first = open_pty()
    numbers = (first.master, first.slave)
    first.close()
    second = open_pty()  # the lowest free numbers: usually the ones just freed
    try:
        first.close()
        os.write(second.master, b"x")  # would be EBADF had the second close reached it
        assert os.read(second.slave, 1) == b"x"
        assert (first.master, first.slave) == (-1, -1) and numbers != (-1, -1)
    finally:
        second.close()
