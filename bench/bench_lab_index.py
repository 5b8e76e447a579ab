"""Benchmark of the lab index on a real PostgreSQL server (started here, in a temporary folder).

Prints:
* the sync rate: four ``rig lab sync`` processes at once, 250 sealed runs each (goal: the 1000
  runs in under 30 s), and one process syncing all 1000; against the baseline of reading the
  same 1000 folders (``list_runs``, what ``rig runs`` does) in one process;
* the query times at 10 000 runs (the 1000 synced plus 9000 copies under other run ids and rigs;
  goal: each under 100 ms), median of 5, on one open connection, against a ``SELECT 1`` round trip.

    .venv/bin/python bench/bench_lab_index.py [--runs 10000]

The server keeps PostgreSQL's durable defaults (fsync on), unlike the tests' throwaway cluster.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from labfixture import PASSWORD, generate_runs, pg_server

RIGS = ("cage-1", "cage-2", "cage-3", "cage-4")
PER_RIG = 250
SYNC_GOAL_S = 30.0
QUERY_GOAL_MS = 100.0


def _median_ms(fn: Callable[[], Any], repeat: int = 5) -> float:
    fn()  # warm: plans cached, pages in memory
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(1000 * (time.perf_counter() - t))
    return statistics.median(times)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--runs", type=int, default=10_000, help="runs in the index for the queries")
    args = ap.parse_args()
    import psycopg

    from rig.lab import queries
    from rig.lab.schema import connect, ensure_schema
    from rig.lab.summary import summarize
    from rig.lab.sync import insert_run, run_folders, sync_runs
    from rig.store import list_runs

    os.environ["PGPASSWORD"] = PASSWORD
    ok = True
    with pg_server(durable=True) as pg, tempfile.TemporaryDirectory() as tmp:
        t = time.perf_counter()
        dirs = []
        for k, rig in enumerate(RIGS):
            d = Path(tmp) / rig
            generate_runs(d, PER_RIG, rig=rig, seed=k, outlier_every=25 if k == 2 else 0)
            dirs.append(d)
        n_runs = len(RIGS) * PER_RIG
        print(f"generated {n_runs} sealed runs (RunWriter) in {time.perf_counter() - t:.1f} s")

        t = time.perf_counter()
        listed = sum(len(list_runs(d)) for d in dirs)
        base_s = time.perf_counter() - t
        print(f"baseline: reading the {listed} run folders (list_runs) takes {base_s:.2f} s")

        pg.psql("CREATE DATABASE lab4 OWNER rig", db="postgres")
        url4 = pg.url.rsplit("/", 1)[0] + "/lab4"
        t = time.perf_counter()
        procs = [subprocess.Popen([sys.executable, "-m", "rig.cli", "lab", "sync", "--runs-dir",
                                   str(d), "--lab", url4], stdout=subprocess.DEVNULL)
                 for d in dirs]  # fmt: skip
        codes = [p.wait() for p in procs]
        sync4_s = time.perf_counter() - t
        with psycopg.connect(url4) as c:
            indexed = c.execute("SELECT count(*) FROM lab_runs").fetchone()[0]  # type: ignore[index]
        good = codes == [0] * 4 and indexed == n_runs and sync4_s < SYNC_GOAL_S
        ok &= good
        print(f"sync, 4 processes at once: {indexed} runs in {sync4_s:.2f} s"
              f" = {indexed / sync4_s:.0f} runs/s (goal: {n_runs} in < {SYNC_GOAL_S:.0f} s)"
              f" {'OK' if good else 'MISSED'}")  # fmt: skip

        folders = [f for d in dirs for f in run_folders(d)]
        t = time.perf_counter()
        report = sync_runs(pg.url, folders)
        sync1_s = time.perf_counter() - t
        print(f"sync, 1 process: {len(report.added)} runs in {sync1_s:.2f} s"
              f" = {len(report.added) / sync1_s:.0f} runs/s")  # fmt: skip
        t = time.perf_counter()
        again = sync_runs(pg.url, folders)
        print(f"re-sync of the same {again.present} runs (nothing to add):"
              f" {time.perf_counter() - t:.2f} s")  # fmt: skip

        # fill to --runs: copies of the synced summaries under other run ids and rigs
        summaries = [s for s in (summarize(f) for f in folders) if s is not None]
        conn = connect(pg.url)
        ensure_schema(conn)
        t = time.perf_counter()
        k = 0
        while len(summaries) * (k + 1) < args.runs:
            k += 1
            for s in summaries[: args.runs - len(summaries) * k]:
                insert_run(conn, dataclasses.replace(
                    s, run_id=f"{s.run_id}-copy{k}", rig=f"{s.rig}-{k % 3}",
                    dut_serial=f"{s.dut_serial}{k}" if k % 2 else s.dut_serial))  # fmt: skip
        conn.autocommit = True
        conn.execute("ANALYZE")
        conn.autocommit = False
        total = conn.execute("SELECT count(*) FROM lab_runs").fetchone()[0]  # type: ignore[index]
        conn.rollback()
        print(f"filled the index to {total} runs in {time.perf_counter() - t:.1f} s")

        base_ms = _median_ms(lambda: conn.execute("SELECT 1").fetchone())
        print(f"\nbaseline: SELECT 1 round trip {base_ms:.2f} ms")
        views: list[tuple[str, Callable[[], Any]]] = [
            ("rig lab runs", lambda: queries.runs(conn)),
            ("rig lab runs --dut SN-0007", lambda: queries.runs(conn, dut="SN-0007")),
            ("rig lab runs --status failed", lambda: queries.runs(conn, status="failed")),
            ("rig lab dut SN-0007", lambda: queries.dut(conn, "SN-0007")),
            ("rig lab trend x0_ut --lot 2", lambda: queries.trend(conn, "x0_ut", lot="2")),
            ("rig lab trend x0_ut (all lots)", lambda: queries.trend(conn, "x0_ut")),
            ("rig lab audit", lambda: queries.audit(conn)),
        ]
        print(f"query times at {total} runs (median of 5; goal < {QUERY_GOAL_MS:.0f} ms each):")
        for name, fn in views:
            ms = _median_ms(fn)
            ok &= ms < QUERY_GOAL_MS
            print(f"  {name:<32} {ms:7.1f} ms  {'OK' if ms < QUERY_GOAL_MS else 'MISSED'}")
        conn.close()
        t = time.perf_counter()
        subprocess.run([sys.executable, "-m", "rig.cli", "lab", "audit", "--lab", pg.url],
                       stdout=subprocess.DEVNULL, check=True)  # fmt: skip
        print(
            f"  (the whole 'rig lab audit' process, start-up included: "
            f"{1000 * (time.perf_counter() - t):.0f} ms)"
        )
    print("\nall goals met" if ok else "\nsome goal MISSED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
