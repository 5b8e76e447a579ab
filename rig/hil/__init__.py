"""Closed-loop hardware in the loop (ADR 0043): a spacecraft's attitude propagated by Basilisk
(the optional ``[hil]`` extra), the field in its body frame made by the cage, the DUT's reading of
it handed to the flight software under test, whose dipole commands turn the spacecraft.

Nothing here talks to a device: the ``closed_loop`` step kind (:mod:`rig.steps.closed_loop`)
carries the field out through the run's cage controller and brings the DUT's readings in;
:func:`rig.hil.loop.software_only` runs the same scenario with a model magnetometer instead, the
all-software run the closed-loop run is compared with.
"""
