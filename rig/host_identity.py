"""Who and where a process is, so that another process can tell whether it may judge it by PID.

A PID means something only inside one PID namespace of one boot of one computer: a reader in a
container, on another host sharing a folder, or after a reboot sees another process (or none)
under the same number. :func:`identity` records the process with its boot id
(``/proc/sys/kernel/random/boot_id``), its PID namespace (``/proc/self/ns/pid``, device and inode)
and its start time (clock ticks after boot, ``/proc/<pid>/stat`` field 22), and :func:`alive`
answers "is that process still running?" only when the asker is provably in the same namespace of
the same boot - otherwise it says it cannot tell (``None``). Linux only; elsewhere every answer is
"cannot tell".
"""

from __future__ import annotations

import os
import socket
from typing import Any


def boot_id() -> str | None:
    """This boot of this computer (a random UUID the kernel makes at boot), None if unknown."""
    try:
        with open("/proc/sys/kernel/random/boot_id", encoding="ascii") as f:
            return f.read().strip() or None
    except OSError:
        return None


def pid_namespace() -> str | None:
    """This process's PID namespace as ``"<device>:<inode>"`` of ``/proc/self/ns/pid``."""
    try:
        st = os.stat("/proc/self/ns/pid")
    except OSError:
        return None
    return f"{st.st_dev}:{st.st_ino}"


def start_ticks(pid: int) -> int | None:
    """When process ``pid`` started (clock ticks after boot), None if it is gone or unknown."""
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii", errors="replace") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    try:
        return int(fields[19])  # field 22 of stat(5); fields[0] is field 3
    except (IndexError, ValueError):
        return None


def identity(pid: int | None = None) -> dict[str, Any]:
    """This process (or process ``pid`` of this host): host name, boot id, PID namespace, PID and
    start time (JSON-ready)."""
    pid = os.getpid() if pid is None else pid
    return {"host": socket.gethostname(), "boot_id": boot_id(), "pid_ns": pid_namespace(),
            "pid": pid, "pid_start": start_ticks(pid)}  # fmt: skip


def same_namespace(ident: Any) -> bool:
    """True when ``ident`` (from :func:`identity`) was taken in this boot and this PID namespace,
    so its PID names the same process here; False when that is not provable."""
    if not isinstance(ident, dict):
        return False
    here_boot, here_ns = boot_id(), pid_namespace()
    return (
        here_boot is not None
        and here_ns is not None
        and ident.get("boot_id") == here_boot
        and ident.get("pid_ns") == here_ns
    )


def alive(ident: Any) -> bool | None:
    """Is the process of ``ident`` still running? ``None`` when this process cannot tell (another
    boot, host or PID namespace, or no PID recorded): then ask something else (a lease)."""
    if not same_namespace(ident):
        return None
    pid = ident.get("pid")
    if not isinstance(pid, int) or isinstance(pid, bool) or pid <= 0:
        return None
    from rig.child_process import process_alive

    if not process_alive(pid):
        return False
    started = ident.get("pid_start")
    return started is None or start_ticks(pid) == started  # the same PID, not a reused one
