"""The interlock in simulated time: the same exclusion, kept in this process.

In simulated time (:mod:`timebase`, ADR 0038) the outputs are simulated devices inside this
process, at wire addresses (``simpipe://coil_x``, a port of the simulated loopback network) that
are names on its simulated clock: no other process can reach them, and another simulation may use
the very same names for its own devices. A lock file in the shared lock folder would therefore
mislead (``rig safe`` or ``rig runs`` of a real rig at such an address would find it held) and
block (two simulations beside each other, the tests in parallel). So the locks of simulated time
are held per simulated clock, in memory: two commands of one simulation still exclude each other
on one output (:class:`~rig.engine.interlock.RigBusyError` naming the holder, as on the wall
clock), nothing is written to the lock folder, and they vanish with the clock.
"""

from __future__ import annotations

import os
import weakref
from typing import Any

_HELD: weakref.WeakKeyDictionary[Any, dict[str, str]] = weakref.WeakKeyDictionary()
"""Per simulated clock: held wire address -> who holds it."""


def take(clock: Any, addresses: dict[str, str], command: str) -> list[str] | tuple[str, str, str]:
    """Hold every address of ``addresses`` (address -> device name) for ``command`` on simulated
    ``clock``: the addresses now held, or, holding nothing, (device name, address, holder) of the
    first one another command holds."""
    held = _HELD.setdefault(clock, {})
    for address, name in sorted(addresses.items()):
        if address in held:
            return name, address, held[address]
    who = f"'{command}' (PID {os.getpid()}, in simulated time)"
    held.update(dict.fromkeys(addresses, who))
    return sorted(addresses)


def give_back(clock: Any, addresses: list[str]) -> None:
    """Let go of ``addresses`` (held by :func:`take` on ``clock``)."""
    held = _HELD.get(clock, {})
    for address in addresses:
        held.pop(address, None)


def holders(clock: Any, addresses: dict[str, tuple[str, ...]]) -> dict[str, str]:
    """Of ``addresses`` (device name -> its addresses), those held on simulated ``clock``: name ->
    who."""
    held = _HELD.get(clock, {})
    return {name: held[a] for name, addrs in addresses.items() for a in addrs if a in held}
