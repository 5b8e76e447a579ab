"""A real PostgreSQL server in a temporary folder, and generated run folders, for the lab index.

Shared by ``tests/lab`` (imported as ``bench.labfixture``) and ``bench/bench_lab_index.py``
(imported as ``labfixture``: a script's folder is on ``sys.path``). Never a mock: Debian's
``postgresql`` package (``/usr/lib/postgresql/<version>/bin``: initdb, pg_ctl) runs a throwaway
cluster on a unix socket in the temporary folder and a free TCP port on 127.0.0.1.

Run folders are written by the real store (:func:`rig.store.new_run`, results, ``close()``), so
they are sealed as a rig's are.
"""

from __future__ import annotations

import contextlib
import os
import random
import shutil
import socket
import subprocess
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

PASSWORD = "s3cret-Lab-pw-7f1c"
"""The ``rig`` role's password: tests check it never shows up in output or run folders."""


def postgres_bin() -> Path | None:
    """The newest ``/usr/lib/postgresql/<version>/bin`` holding initdb, or None."""
    found = sorted(
        Path("/usr/lib/postgresql").glob("*/bin/initdb"),
        key=lambda p: int(p.parent.parent.name) if p.parent.parent.name.isdigit() else 0,
    )
    return found[-1].parent if found else None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass(frozen=True)
class PgServer:
    """A running throwaway cluster."""

    folder: Path
    port: int
    socket_dir: Path
    bin_dir: Path

    @property
    def admin_url(self) -> str:
        """Superuser over the unix socket (trust), database ``lab``."""
        return f"postgresql://postgres@/lab?host={self.socket_dir}&port={self.port}"

    @property
    def url(self) -> str:
        """The ``rig`` role over TCP with no password in it (scram-sha-256: PGPASSWORD/.pgpass)."""
        return f"postgresql://rig@127.0.0.1:{self.port}/lab"

    @property
    def url_with_password(self) -> str:
        """The same with the password written in (as some admins would)."""
        return f"postgresql://rig:{PASSWORD}@127.0.0.1:{self.port}/lab"

    def psql(self, sql: str, db: str = "lab") -> str:
        """Run SQL as the superuser; its output (unaligned, tuples only)."""
        out = subprocess.run(
            [str(self.bin_dir / "psql"), "-X", "-At", "-h", str(self.socket_dir),
             "-p", str(self.port), "-U", "postgres", "-d", db, "-c", sql],
            capture_output=True, text=True, check=True,
        )  # fmt: skip
        return out.stdout.strip()

    def stop(self) -> None:
        """Stop the server (fast shutdown); the folder stays until :func:`pg_server` removes it."""
        _as_owner(self.folder, [str(self.bin_dir / "pg_ctl"), "-D", str(self.folder / "data"),
                                "-m", "fast", "-w", "stop"], check=False)  # fmt: skip

    def start(self) -> None:
        """Start (or restart) the server and wait until it accepts connections."""
        opts = f"-p {self.port} -k {self.socket_dir} -c listen_addresses=127.0.0.1"
        _as_owner(self.folder, [str(self.bin_dir / "pg_ctl"), "-D", str(self.folder / "data"),
                                "-l", str(self.folder / "log"), "-o", opts, "-w", "start"])  # fmt: skip


def _as_owner(folder: Path, argv: list[str], check: bool = True) -> None:
    """Run a PostgreSQL server program as the folder's owner (initdb refuses root)."""
    if os.geteuid() == 0:
        argv = ["runuser", "-u", "postgres", "--", *argv]
    subprocess.run(argv, check=check, capture_output=True, text=True, cwd=folder)


@contextlib.contextmanager
def pg_server(*, durable: bool = False) -> Iterator[PgServer]:
    """A fresh cluster with a database ``lab`` and a role ``rig`` (password :data:`PASSWORD`).

    ``durable`` False turns fsync off (tests: speed); the benchmark keeps PostgreSQL's defaults.
    """
    bin_dir = postgres_bin()
    if bin_dir is None:
        raise RuntimeError("no PostgreSQL server binaries under /usr/lib/postgresql")
    folder = Path(tempfile.mkdtemp(prefix="riglab-"))
    if os.geteuid() == 0:
        shutil.chown(folder, "postgres", "postgres")
    server = PgServer(folder, _free_port(), folder, bin_dir)
    try:
        _as_owner(folder, [str(bin_dir / "initdb"), "-D", str(folder / "data"), "-U", "postgres",
                           "--auth-local=trust", "--auth-host=scram-sha-256", "-E", "UTF8",
                           "--no-sync"])  # fmt: skip
        if not durable:
            with (folder / "data" / "postgresql.conf").open("a") as fh:
                fh.write("fsync = off\nsynchronous_commit = off\nfull_page_writes = off\n")
        server.start()
        server.psql(f"CREATE ROLE rig LOGIN PASSWORD '{PASSWORD}'", db="postgres")
        server.psql("CREATE DATABASE lab OWNER rig", db="postgres")
        yield server
    finally:
        server.stop()
        shutil.rmtree(folder, ignore_errors=True)


RIG_TOML = """\
[lab]
rig = "{rig}"

[devices.reference]
kind = "ascii-mag"
protocol = "serial"
path = "/dev/ttyUSB0"
serial = "FGM-{ref_serial}"
calibrated_on = {calibrated_on}
certificate_expires = {expires}

[devices.dut]
kind = "ascii-mag"
protocol = "serial"
path = "/dev/ttyUSB1"
"""


def generate_runs(
    runs_dir: Path,
    n: int,
    *,
    rig: str,
    seed: int,
    duts: int = 40,
    lots: int = 5,
    outlier_every: int = 0,
) -> list[Path]:
    """``n`` closed, sealed runs of ``rig`` under ``runs_dir``: DUT serials ``SN-0000`` ...,
    lots ``1..lots``, mostly PASS, a calibration result (offsets in uT with sigma) and an acceptance
    verdict; every 10th run used a reference whose certificate had expired (2020-06-30); every
    ``outlier_every``-th run (0: none) has an x offset 3 uT off its lot's."""
    from rig.store import new_run

    rnd = random.Random(seed)
    folders = []
    for i in range(n):
        dut = f"SN-{rnd.randrange(duts):04d}"
        lot = str(1 + int(dut[3:]) % lots)
        offset = 1.5 + 0.1 * int(lot) + rnd.gauss(0, 0.05)
        if outlier_every and i % outlier_every == outlier_every - 1:
            offset += 3.0  # a rig with a problem: an offset far outside the lot's spread
        rms = abs(rnd.gauss(30, 8))
        w = new_run(
            runs_dir, f"{dut}-{i}", procedure="DUT acceptance", procedure_file="dut-acceptance.yaml",
            parameters={"dut_serial": dut, "lot": lot, "operator": "ana"}, operator="ana",
            dut_serial=dut, software_version="0.1.0", magnetometers=["reference", "dut"], loads=[],
        )  # fmt: skip
        expired = i % 10 == 0
        (w.folder / "rig.toml").write_text(
            RIG_TOML.format(rig=rig, ref_serial=100 + (i % 3),
                            calibrated_on="2019-06-30" if expired else "2026-01-15",
                            expires="2020-06-30" if expired else "2027-01-15"),
            encoding="utf-8",
        )  # fmt: skip
        w.add_sample(0.0, "dut", (offset, 20.0, -30.0))
        w.set_result(
            "calibrate",
            {"model": "scalar", "springmann": {"a": 1.0 + rnd.gauss(0, 1e-3), "x0_ut": offset,
                                               "y0_ut": -0.4, "z0_ut": 0.2},
             "sigma": {"springmann": {"a": 2e-4, "x0_ut": 0.01, "y0_ut": 0.01, "z0_ut": 0.01}},
             "residual_rms_nt": rms},
        )  # fmt: skip
        fail = rms > 45
        w.set_result(
            "verdict",
            {"overall": "FAIL" if fail else "PASS", "criteria": [
                {"name": "residual rms", "value": rms, "unit": "nT", "min": None, "max": 45.0,
                 "verdict": "FAIL" if fail else "PASS"},
                {"name": "x offset", "value": offset, "unit": "uT", "min": -5.0, "max": 5.0,
                 "verdict": "PASS"}]},
        )  # fmt: skip
        (w.folder / "report.txt").write_text(f"report of {w.folder.name}\n", encoding="utf-8")
        w.close("failed" if fail else "complete", "generated")
        folders.append(w.folder)
    return folders
