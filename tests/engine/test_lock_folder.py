"""The interlock's lock folder against other local accounts: a folder another user made first (with
links planted in it), a world-writable one, links and hard links to a file of ours, a second
account on a private folder and on a shared group folder, and aliases of one supply's address.

Real files, real processes and real accounts (``setpriv`` as root; skipped with the reason where
it is missing or not permitted). The rig configuration names supplies on ports where nothing
listens: every refusal here comes before a device is opened.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from rig.config import load_rig_config
from rig.engine.interlock import (
    RigBusyError,
    RigLock,
    _lock_name,
    lock_addresses,
    output_devices,
)

pytestmark = pytest.mark.realtime

NOBODY = 65534
SHARED_GID = 4242  # a group for the shared-folder test (numeric: it needs no /etc/group line)

RIG_TOML = """
[cage]
axes = {{ x = "coil_x", y = "coil_y", z = "coil_z" }}
max_current_a = [2.0, 2.0, 2.0]
max_field_ut = 150.0
max_slew_a_per_s = 4.0

[devices.coil_x]
kind = "riden-rd60xx"
protocol = "modbus-tcp"
host = "{host}"
port = 9

[devices.coil_y]
kind = "riden-rd60xx"
protocol = "modbus-tcp"
host = "127.0.0.1"
port = {port_y}

[devices.coil_z]
kind = "riden-rd60xx"
protocol = "modbus-tcp"
host = "127.0.0.1"
port = {port_z}
"""

TAKE_LOCK = """
import sys
from rig.config import load_rig_config
from rig.engine.interlock import RigLock
with RigLock(load_rig_config(sys.argv[1]), "member") as lock:
    print("locked", len(lock.fds))
"""

PRECIOUS = b"root's own file: must never be overwritten\n"


def as_root() -> None:
    if os.geteuid() != 0:
        pytest.skip("acting as another account needs root (setpriv); run the tests as root")
    if shutil.which("setpriv") is None:
        pytest.skip("setpriv (util-linux) is not installed")


@pytest.fixture
def shared_tmp() -> Iterator[Path]:
    """A folder every account may read (pytest's tmp_path is private to root)."""
    folder = Path(tempfile.mkdtemp(prefix="rig-lock-test-"))
    folder.chmod(0o755)
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def rig_toml(
    folder: Path, host: str = "127.0.0.1", name: str = "rig.toml", others: int = 10
) -> Path:
    """A rig configuration with coil_x on ``host`` port 9, coil_y and coil_z on 127.0.0.1 ports
    ``others`` and ``others + 1``."""
    path = folder / name
    path.write_text(RIG_TOML.format(host=host, port_y=others, port_z=others + 1))
    path.chmod(0o644)
    return path


def set_field(rig: Path, lock_folder: Path, *, user: int | None = None,
              groups: str = "--clear-groups") -> subprocess.CompletedProcess[str]:  # fmt: skip
    """`rig cage set-field 0 0 0` with ``lock_folder``, as ``user`` (root when None)."""
    argv = [sys.executable, "-m", "rig.cli", "cage", "set-field", "0", "0", "0",
            "--rig-config", str(rig)]  # fmt: skip
    if user is not None:
        argv = ["setpriv", f"--reuid={user}", f"--regid={user}", groups, *argv]
    env = {**os.environ, "RIG_LOCK_DIR": str(lock_folder)}
    return subprocess.run(argv, capture_output=True, text=True, timeout=60, env=env,
                          cwd=rig.parent)  # fmt: skip


def one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err and "internal error" not in err, err
    return lines[0]


def lock_files_of(rig: Path) -> list[str]:
    return sorted(
        _lock_name(a)
        for addresses in output_devices(load_rig_config(rig)).values()
        for a in addresses
    )


def test_another_users_folder_with_a_planted_link_is_refused_and_nothing_is_written(
    shared_tmp: Path,
) -> None:
    """The attack of issue 29: another account makes the lock folder first and plants every lock
    file as a link to a file of ours; we refuse the folder and write nothing anywhere."""
    as_root()
    rig = rig_toml(shared_tmp)
    victim = shared_tmp / "victim.conf"
    victim.write_bytes(PRECIOUS)
    evil = shared_tmp / "locks"
    evil.mkdir(mode=0o777)
    evil.chmod(0o777)
    for name in lock_files_of(rig):
        (evil / name).symlink_to(victim)
    os.lchown(evil, NOBODY, NOBODY)
    for entry in evil.iterdir():
        os.lchown(entry, NOBODY, NOBODY)
    before = sorted(p.name for p in evil.iterdir())
    done = set_field(rig, evil)
    assert done.returncode == 2
    line = one_line(done.stderr)
    assert "belongs to nobody" in line and "2770" in line, line
    assert victim.read_bytes() == PRECIOUS
    assert sorted(p.name for p in evil.iterdir()) == before
    # the same folder ours but world-writable (a 1777 folder like /tmp) is refused too
    os.chown(evil, 0, 0)
    done = set_field(rig, evil)
    assert done.returncode == 2 and "anyone may write to it" in one_line(done.stderr)
    assert victim.read_bytes() == PRECIOUS


def test_links_and_hard_links_in_our_own_folder_are_refused(tmp_path: Path) -> None:
    """A group member (or an old version's leftovers) cannot make us write through a lock file:
    a symbolic link is never followed, a hard link or a foreign file never written."""
    rig = rig_toml(tmp_path)
    victim = tmp_path / "victim.conf"
    victim.write_bytes(PRECIOUS)
    first = lock_files_of(rig)[0]
    locks = tmp_path / "locks"
    locks.mkdir(mode=0o700)
    (locks / first).symlink_to(victim)
    done = set_field(rig, locks)
    assert done.returncode == 2 and "is a symbolic link" in one_line(done.stderr), done.stderr
    (locks / first).unlink()
    os.link(victim, locks / first)
    done = set_field(rig, locks)
    assert done.returncode == 2 and "links (a hard link" in one_line(done.stderr), done.stderr
    (locks / first).unlink()
    (locks / first).mkdir()
    done = set_field(rig, locks)
    assert done.returncode == 2 and "not a regular file" in one_line(done.stderr), done.stderr
    assert victim.read_bytes() == PRECIOUS
    (locks / first).rmdir()
    # a folder given as a link (the name could be anybody's) is refused as well
    link = tmp_path / "link-to-locks"
    link.symlink_to(locks)
    done = set_field(rig, link)
    assert done.returncode == 2 and "symbolic link" in one_line(done.stderr), done.stderr


def test_a_missing_folder_is_created_private_and_lock_files_0600(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rig = rig_toml(tmp_path)
    folder = tmp_path / "new" / "locks"
    monkeypatch.setenv("RIG_LOCK_DIR", str(folder))
    old = os.umask(0o022)
    try:
        with RigLock(load_rig_config(rig), "test") as lock:
            assert len(lock.fds) == 3
    finally:
        os.umask(old)
    assert folder.stat().st_mode & 0o7777 == 0o700
    files = list(folder.iterdir())
    assert len(files) == 3 and all(f.stat().st_mode & 0o777 == 0o600 for f in files)
    record = json.loads(files[0].read_text())
    assert record["command"] == "test" and record["process"]["pid"] == os.getpid()


def test_second_user_on_a_private_folder_gets_one_line(shared_tmp: Path) -> None:
    """Root used the rig first (the folder is root's, 0700); another account gets one line that
    says how to share it, exit 2, no traceback (it was a PermissionError, exit 1)."""
    as_root()
    rig = rig_toml(shared_tmp)
    locks = shared_tmp / "locks"
    done = set_field(rig, locks)  # root: takes the locks, then cannot reach the supplies
    assert done.returncode == 2 and "cannot connect" in done.stderr, done.stderr
    assert locks.stat().st_mode & 0o7777 == 0o700
    other = set_field(rig, locks, user=NOBODY)
    if "setpriv" in other.stderr and other.returncode != 2:
        pytest.skip(f"setpriv cannot switch accounts here: {other.stderr.strip()}")
    assert other.returncode == 2, other.stderr
    line = one_line(other.stderr)
    assert "is not shared with you" in line and "chmod 2770" in line, line


def test_accounts_of_a_shared_group_folder_take_turns(
    shared_tmp: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The documented lab setup: root's folder, group GROUP, mode 2770. Root's lock files are
    the group's (0660), so another member is refused in one line while root holds the rig and
    takes it once root has let go; its own lock files stay the group's."""
    as_root()
    rig = rig_toml(shared_tmp)
    locks = shared_tmp / "locks"
    locks.mkdir()
    os.chown(locks, 0, SHARED_GID)
    locks.chmod(0o2770)
    member = f"--groups={SHARED_GID}"
    monkeypatch.setenv("RIG_LOCK_DIR", str(locks))
    with RigLock(load_rig_config(rig), "rig cage set-field (root)"):
        files = list(locks.iterdir())
        assert files and all(
            f.stat().st_gid == SHARED_GID and f.stat().st_mode & 0o777 == 0o660 for f in files
        )
        busy = set_field(rig, locks, user=NOBODY, groups=member)
        if "setpriv" in busy.stderr and busy.returncode != 2:
            pytest.skip(f"setpriv cannot switch accounts here: {busy.stderr.strip()}")
        line = one_line(busy.stderr)
        assert busy.returncode == 2 and "is in use by 'rig cage set-field (root)'" in line
    free = subprocess.run(
        ["setpriv", f"--reuid={NOBODY}", f"--regid={NOBODY}", member, sys.executable, "-c",
         TAKE_LOCK, str(rig)], capture_output=True, text=True, timeout=60,
        env={**os.environ, "RIG_LOCK_DIR": str(locks)}, cwd=shared_tmp,
    )  # fmt: skip
    assert free.returncode == 0 and free.stdout.strip() == "locked 3", free.stderr
    assert all(f.stat().st_gid == SHARED_GID for f in locks.iterdir())
    # a non-member may not use the folder at all
    outsider = set_field(rig, locks, user=NOBODY)
    assert outsider.returncode == 2 and "you are not in that group" in one_line(outsider.stderr)


def test_localhost_and_127_0_0_1_take_the_same_lock(tmp_path: Path) -> None:
    """Two configurations naming one supply by its name and by its address collide (coil_x is
    the only supply they share)."""
    by_name = load_rig_config(rig_toml(tmp_path, "localhost", "by-name.toml"))
    by_address = load_rig_config(rig_toml(tmp_path, "127.0.0.1", "by-address.toml", others=20))
    assert "modbus-tcp 127.0.0.1:9 id 1" in lock_addresses(by_name.devices["coil_x"])
    busy = r"coil_x \(modbus-tcp 127\.0\.0\.1:9 id 1\) is in use by 'rig run by-name'"
    with RigLock(by_name, "rig run by-name"), pytest.raises(RigBusyError, match=busy):
        RigLock(by_address, "rig run by-address").acquire()
    with RigLock(by_address, "again"):  # released: the other one may go
        pass
