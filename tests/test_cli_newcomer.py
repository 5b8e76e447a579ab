"""What a newcomer tripped over (issue 13), through the real ``rig`` command and real run folders:
run ids for ``rig calibrate``, ``rig check`` without a rig, ``-q`` hiding errors, closed pipes,
``rig runs`` verdicts, ``rig show`` summary and ``--json``, export time bases, the duration of a
cage characterization, empty ``--set`` values and the smoke procedure's report."""

from __future__ import annotations

import contextlib
import csv
import datetime as dt
import io
import json
import math
import os
import re
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from rig.cli import EXIT_CLOSED_PIPE, main
from rig.config import load_rig_config
from rig.engine.cpu_wait import CpuWaitLog
from rig.procedure.language import parse_procedure
from rig.procedure.plan import (
    characterization_duration_s,
    compile_plan,
    dry_run,
    rig_timing,
)
from rig.procedure_files import find_procedure
from rig.store import RunReader
from rig.store.export import export_csv, export_hdf5
from rig.store.run_store import new_run
from tests.simproc import sim_process

pytestmark = pytest.mark.simcage

START_UTC = "2026-03-04T05:06:07+00:00"
START_MONO = 1000.0

CHECK_HEAD = "procedure: T\nparameters:\n  dut_serial: {default: A1}\nsteps:\n"

RIG_TOML = """
[cage]
axes = { x = "coil_x", y = "coil_y", z = "coil_z" }
max_current_a = [2.5, 2.5, 2.5]
max_field_ut = 120.0
max_slew_a_per_s = 10.0
nominal_k_ut_per_a = [[40.0, 0.0, 0.0], [0.0, 40.0, 0.0], [0.0, 0.0, 40.0]]
"""
for _port, _name in enumerate(("coil_x", "coil_y", "coil_z", "load_bus"), 9):
    RIG_TOML += f"""
[devices.{_name}]
kind = "riden-rd60xx"
protocol = "modbus-tcp"
host = "127.0.0.1"
port = {_port}
device_id = 1
"""
RIG_TOML += """
[devices.dut]
kind = "hmr2300"
protocol = "serial"
path = "/dev/no-such-dut"
baudrate = 19200

[devices.reference]
kind = "ascii-mag"
protocol = "serial"
path = "/dev/no-such-reference"
baudrate = 115200
"""
"""A rig whose instruments are not there (port 9 on loopback refuses): loads fine, cannot run."""


def rig(*args: str, **kw: Any) -> subprocess.CompletedProcess[str]:
    """The command line exactly as a user runs it."""
    return subprocess.run(
        [sys.executable, "-m", "rig.cli", *args], capture_output=True, text=True, **kw
    )


def make_run(
    runs: Path,
    label: str,
    *,
    verdict: str | None = None,
    big_result: bool = False,
) -> Path:
    """A real run folder written by the run store, with a known time base."""
    w = new_run(runs, label, procedure="Made up", procedure_file="made.yaml", dut_serial=label,
                operator="ana", magnetometers={"dut": "dut", "reference": "reference"},
                loads=["load_bus"], instruments={"coil_x": "RD6006P SN 1", "dut": "HMR2300 0123"})  # fmt: skip
    w.set_meta(start_time=START_UTC, start_monotonic=START_MONO)
    # the DUT at 10 Hz from t_run 0.025 s, the reference at 20 Hz from 0 with a linear field, a gap
    for i in range(40):
        t = START_MONO + 0.025 + 0.1 * i
        w.add_sample(t, "dut", (float(i), 0.0, 1.0))
    for i in range(80):
        t = START_MONO + 0.05 * i
        if 1.0 <= t - START_MONO < 2.0:
            continue  # the reference was silent for a second
        w.add_sample(t, "reference", (10.0 * (t - START_MONO), -1.0, 2.0))
    w.add_channel(START_MONO + 0.5, "load_bus", 0.8, None)
    w.add_channel(START_MONO + 0.6, "load_bus", None, 0.79)
    w.add_channel(START_MONO + 3.0, "load_bus", 0.0, None)
    w.set_step(0, "noise floor", "null_field", START_MONO, START_MONO + 2.25)
    w.set_step(1, "sweep", "sphere_sweep", START_MONO + 2.25, START_MONO + 4.0)
    w.set_result("noise floor", {"dut_noise_nt": 41.5, "reference_noise_nt": 11.0})
    fit: dict[str, Any] = {"model": "vector", "residual_rms_nt": 25.25, "p": math.nan}
    if big_result:
        fit["history"] = [[float(i), float(i) / 3] for i in range(5000)]
    w.set_result("vector calibration", fit)
    if verdict is not None:
        w.set_result("verdict", {"overall": verdict, "criteria": [
            {"name": "DUT noise floor", "value": 41.5, "unit": "nT", "min": None, "max": 60,
             "margin": 18.5, "verdict": "PASS"},
            {"name": "fit residual", "value": 25.25, "unit": "nT", "min": None, "max": 20,
             "margin": -5.25, "verdict": "FAIL" if verdict == "FAIL" else "PASS"},
        ]})  # fmt: skip
    w.close("failed" if verdict == "FAIL" else "complete", "made up")
    return w.folder


# --- 1. rig calibrate RUN-ID --------------------------------------------------------------------


@pytest.fixture(scope="module")
def sim_runs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, Path]]:
    """On ``rig sim``: the shipped smoke procedure, then a cage characterization and a sphere
    sweep. Yields (rig configuration, runs folder)."""
    folder = tmp_path_factory.mktemp("sim")
    runs = folder / "runs"
    with sim_process(folder) as (rig_toml, _):
        args = ["-q", "run", "smoke", "--rig", str(rig_toml), "--yes", "--runs-dir", str(runs)]
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            assert main([*args, "--set", "dut_serial=SN-NEWCOMER"]) == 0
        assert out.getvalue() == ""  # -q and a complete run: not a word (prompts included)
        proc = folder / "sweep.yaml"
        proc.write_text(
            "procedure: characterize and sweep\nparameters:\n  dut_serial: {default: SN-SWEEP}\n"
            "steps:\n  - characterize_cage: {amplitude_a: 1.0, samples: 5, repeats: 1}\n"
            "    name: cage model\n"
            "  - sphere_sweep: {directions: 16, magnitude_ut: [20, 40], dwell_s: 0.8}\n"
        )
        waits = [CpuWaitLog(), *(CpuWaitLog(pid=pid) for pid in _children())]  # rig, simulator
        t_start = time.monotonic()
        for log in waits:
            log.note(t_start)
        assert main(["-q", "run", str(proc), "--rig", str(rig_toml), "--yes",
                     "--runs-dir", str(runs)]) == 0  # fmt: skip
        for log in waits:
            log.note(time.monotonic())
        waited_s = sum(log.waited_since(t_start) for log in waits)
        (folder / "cpu_wait_s").write_text(f"{waited_s}\n", encoding="utf-8")
        yield rig_toml, runs


def _children() -> list[int]:
    """Process ids of this process's children (the simulator), from /proc."""
    pids = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[1]) == os.getpid():
            pids.append(int(stat.parent.name))
    return pids


def run_folder(runs: Path, label: str) -> Path:
    return next(p for p in runs.iterdir() if p.name.endswith(label))


def test_calibrate_takes_a_bare_run_id(sim_runs: tuple[Path, Path], tmp_path: Path) -> None:
    _, runs = sim_runs
    folder = run_folder(runs, "SN-SWEEP")
    out = tmp_path / "result.json"
    proc = rig("calibrate", folder.name, "--runs-dir", str(runs), "--out", str(out), cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "residual" in proc.stdout and json.loads(out.read_text())["model"] == "vector"
    # the folder path still works, and a name that is neither says what was looked for
    by_path = rig("-q", "calibrate", str(folder), cwd=tmp_path)
    assert by_path.returncode == 0, by_path.stderr
    nothing = rig("calibrate", "20990101-000000-X", "--runs-dir", str(runs), cwd=tmp_path)
    assert nothing.returncode == 2 and len(nothing.stderr.splitlines()) == 1
    assert (
        "no CSV file or run '20990101-000000-X'" in nothing.stderr and "rig runs" in nothing.stderr
    )


# --- 10. smoke writes its report ----------------------------------------------------------------


def test_smoke_runs_on_the_simulator_and_writes_its_report(sim_runs: tuple[Path, Path]) -> None:
    folder = run_folder(sim_runs[1], "SN-NEWCOMER")
    assert any(s.kind == "report" for s in parse_procedure(find_procedure("smoke")).steps)
    for name in ("report.html", "report.pdf"):
        assert (folder / name).stat().st_size > 10_000, name
    text = (folder / "report.txt").read_text()
    assert "SN-NEWCOMER" in text and "DUT noise at null field" in text and "VERDICT: PASS" in text


# --- 8. the characterization's duration ---------------------------------------------------------


def test_characterization_counts_its_sweep_in_the_dry_run(tmp_path: Path) -> None:
    p = tmp_path / "c.yaml"
    p.write_text(
        CHECK_HEAD + "  - characterize_cage: {amplitude_a: 1.0, samples: 10, repeats: 2}\n"
    )
    dr = dry_run(parse_procedure(p))
    # 28 points, each 0.2 s transient + 10.5 reference periods at 20 Hz, plus 80 ramp set-points
    assert dr.duration_s == pytest.approx(28 * (0.2 + 10.5 / 20) + 80 * 0.05)
    assert characterization_duration_s(1.0, 10, 4) > 1.9 * characterization_duration_s(1.0, 10, 2)
    shipped = dry_run(parse_procedure(find_procedure("cage-characterization")))
    assert shipped.timeline[2][0] > 20.0  # the null check starts after the ~25 s sweep


def test_characterization_estimate_within_20_percent_of_the_simulator(
    sim_runs: tuple[Path, Path],
) -> None:
    rig_toml, runs = sim_runs
    folder = run_folder(runs, "SN-SWEEP")
    reader = RunReader(folder)
    (_, _, kind, t0, t1), *_ = reader.steps()
    reader.close()
    assert kind == "characterize_cage" and t1 is not None
    proc = parse_procedure(folder / "procedure.yaml")
    estimate = next(compile_plan(proc, rig_timing(load_rig_config(rig_toml)))).duration_s
    # on a busy computer the step also waits for this process and the simulator to get a CPU
    # (readings arrive late, replies come late): that time is the computer's, not the plan's
    waited_s = float((runs.parent / "cpu_wait_s").read_text())
    print(f"characterization: measured {t1 - t0:.2f} s, estimated {estimate:.2f} s"
          f" ({waited_s:.2f} s of the run waiting for a CPU)")  # fmt: skip
    assert estimate < 1.2 * (t1 - t0)
    assert t1 - t0 - waited_s < 1.2 * estimate


# --- 2. rig check without a rig -----------------------------------------------------------------


def test_check_without_rig_does_not_claim_ok(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    p = tmp_path / "big.yaml"
    p.write_text(CHECK_HEAD + "  - set_field: {field_ut: [500, 0, 0], hold_s: 1}\n")
    assert main(["check", str(p)]) == 1
    out = capsys.readouterr().out
    assert "OK" not in out
    assert "NOT CHECKED: no rig configuration given (--rig CONFIG.toml)" in out
    # with the rig's limits the same plan is a violation; a harmless one passes
    cfg = tmp_path / "rig.toml"
    cfg.write_text(RIG_TOML)
    assert main(["check", str(p), "--rig", str(cfg)]) == 1
    out = capsys.readouterr().out
    assert "LIMIT:" in out and "exceeds the 120 uT limit" in out and "OK" not in out
    p.write_text(CHECK_HEAD + "  - set_field: {field_ut: [50, 0, 0], hold_s: 1}\n")
    assert main(["check", str(p), "--rig", str(cfg)]) == 0
    assert f"OK: within the limits of {cfg}" in capsys.readouterr().out


def test_check_without_rig_still_checks_absolute_field_sanity(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    p = tmp_path / "nt.yaml"
    p.write_text(CHECK_HEAD + "  - set_field: {field_ut: [30000, 0, 0]}\n")  # nT written as uT
    assert main(["-q", "check", str(p)]) == 1
    out = capsys.readouterr().out
    assert "LIMIT:" in out and "30000.0 uT exceeds 1000 uT" in out


# --- 9. empty --set values ----------------------------------------------------------------------


def test_empty_set_value_is_refused_with_the_fix(capsys: pytest.CaptureFixture[str]) -> None:
    for value in ("dut_serial=", "dut_serial=  "):
        assert main(["check", "smoke", "--set", value]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1
        assert "--set dut_serial= is empty" in err and "--set dut_serial=VALUE" in err
        assert "default 'SN-0001'" in err


# --- 3. -q prints errors, not nothing -----------------------------------------------------------


def test_quiet_run_that_errors_says_so_on_stderr(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = tmp_path / "rig.toml"
    cfg.write_text(RIG_TOML)
    args = ["-q", "run", "smoke", "--rig", str(cfg), "--yes", "--runs-dir", str(tmp_path / "r")]
    assert main(args) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert len(err.splitlines()) == 1
    assert err.startswith("rig: error: run ") and "ended with status error" in err
    assert "coil_x" in err and "cannot connect" in err


# --- 4. closed pipes ----------------------------------------------------------------------------


def _closed_pipe_run(*args: str) -> subprocess.CompletedProcess[bytes]:
    """Run with stdout a pipe whose reader has already gone (``| head`` that has read enough)."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        return subprocess.run([sys.executable, "-m", "rig.cli", *args], stdout=write_end,
                              stderr=subprocess.PIPE, timeout=60)  # fmt: skip
    finally:
        os.close(write_end)


@pytest.mark.parametrize(
    "args",
    [
        ["show", "RUN"],
        ["show", "RUN", "--json"],  # > 64 kB: the pipe breaks inside print, not at the last flush
        ["runs"],
        ["check", "smoke"],
        ["export", "RUN"],
    ],
)
def test_closed_stdout_pipe_ends_quietly(tmp_path: Path, args: list[str]) -> None:
    folder = make_run(tmp_path / "runs", "SN-7", verdict="PASS", big_result=True)
    args = [folder.name if a == "RUN" else a for a in args]
    if args[0] != "check":
        args += ["--runs-dir", str(tmp_path / "runs")]
    proc = _closed_pipe_run(*args)
    assert proc.stderr == b""
    assert proc.returncode == EXIT_CLOSED_PIPE


def test_closed_pipe_through_head(tmp_path: Path) -> None:
    folder = make_run(tmp_path / "runs", "SN-8", verdict="PASS", big_result=True)
    cmd = (f"set -o pipefail; {sys.executable} -m rig.cli show {folder.name} --json"
           f" --runs-dir {tmp_path / 'runs'} | head -n 2")  # fmt: skip
    proc = subprocess.run(["bash", "-c", cmd], capture_output=True, text=True, timeout=60)
    assert proc.stdout.splitlines() == ["{", f'  "run_id": "{folder.name}",']
    assert proc.stderr == "" and proc.returncode == EXIT_CLOSED_PIPE


# --- 5. rig runs shows the verdict --------------------------------------------------------------


def test_runs_lists_the_verdict(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    runs = tmp_path / "runs"
    made = {v: make_run(runs, f"SN-{v or 'none'}", verdict=v) for v in ("PASS", "FAIL", None)}
    assert main(["runs", "--runs-dir", str(runs)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == ["RUN", "STATUS", "VERDICT", "PROCEDURE", "DUT"]
    by_id = {line.split()[0]: line.split() for line in lines[1:]}
    assert by_id[made["PASS"].name][1:3] == ["complete", "PASS"]
    assert by_id[made["FAIL"].name][1:3] == ["failed", "FAIL"]
    assert by_id[made[None].name][1:3] == ["complete", "-"]


# --- 6. rig show: a summary; --json: everything -------------------------------------------------


def test_show_is_a_human_summary(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    folder = make_run(tmp_path / "runs", "SN-42", verdict="FAIL")
    assert main(["show", folder.name, "--runs-dir", str(tmp_path / "runs")]) == 0
    out = capsys.readouterr().out
    with pytest.raises(json.JSONDecodeError):
        json.loads(out)
    for pattern in (
        rf"^run +{folder.name} ",
        r"^procedure +Made up \(made\.yaml\)",
        r"^DUT +SN-42 +operator ana$",
        r"^status +failed \(made up\)$",
        rf"^time +{re.escape(START_UTC)} to \S+ \(\d+ s\)$",
        r"^ +coil_x +RD6006P SN 1$",
        r"^ +dut +HMR2300 0123$",
        r"^samples +dut 40, reference 60$",
        r"^ +1 noise floor +null_field +2\.2 s$",
        r"^ +2 sweep +sphere_sweep +1\.8 s$",
        r"^ +noise floor +dut_noise_nt 41\.5, reference_noise_nt 11$",
        r"^ +vector calibration +model vector, residual_rms_nt 25\.25, p nan$",
        r"^ +PASS DUT noise floor +41\.5 nT +\(max 60\)$",
        r"^ +FAIL fit residual +25\.25 nT +\(max 20\)$",
        r"^VERDICT: FAIL$",
    ):
        assert re.search(pattern, out, re.M), (pattern, out)


def test_show_json_is_all_of_it_and_only_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = make_run(tmp_path / "runs", "SN-43", verdict="PASS")
    assert main(["show", folder.name, "--runs-dir", str(tmp_path / "runs"), "--json"]) == 0
    out = capsys.readouterr().out
    doc = json.loads(out)  # the whole of stdout; NaN (not JSON) became null
    assert "NaN" not in out and doc["results"]["vector calibration"]["p"] is None
    assert doc["run_id"] == folder.name and doc["meta"]["operator"] == "ana"
    assert doc["samples"] == {"dut": 40, "reference": 60}
    assert [s["name"] for s in doc["steps"]] == ["noise floor", "sweep"]
    assert doc["steps"][0]["duration_s"] == pytest.approx(2.25)
    assert doc["results"]["verdict"]["overall"] == "PASS"


# --- 7. export time bases -----------------------------------------------------------------------


def test_csv_export_has_utc_run_time_and_an_aligned_table(tmp_path: Path) -> None:
    folder = make_run(tmp_path / "runs", "SN-9")
    assert main(["-q", "export", str(folder), "--out", str(tmp_path / "csv")]) == 0
    with (tmp_path / "csv" / "samples_aligned.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["t_utc", "t_run_s", "t_s", "dut_x_ut", "dut_y_ut", "dut_z_ut",
                             "reference_x_ut", "reference_y_ut", "reference_z_ut",
                             "load_bus_commanded_a", "load_bus_measured_a"]  # fmt: skip
    assert len(rows) == 40
    start = dt.datetime.fromisoformat(START_UTC)
    for i, row in enumerate(rows):
        t_run = 0.025 + 0.1 * i
        assert float(row["t_run_s"]) == pytest.approx(t_run)
        assert dt.datetime.fromisoformat(row["t_utc"]) == start + dt.timedelta(
            milliseconds=round(1000 * t_run)
        )
        if 0.95 < t_run < 2.0:  # inside the reference's gap: nothing invented
            assert row["reference_x_ut"] == ""
        else:  # the reference's linear field, interpolated to the DUT's time
            assert float(row["reference_x_ut"]) == pytest.approx(10.0 * t_run)
            assert float(row["reference_z_ut"]) == pytest.approx(2.0)
        commanded = "" if t_run < 0.5 else ("0.8" if t_run < 3.0 else "0.0")
        assert row["load_bus_commanded_a"] == commanded
        assert row["load_bus_measured_a"] == ("" if t_run < 0.6 else "0.79")
    # the original files keep their columns; meta.json says how to convert them
    with (tmp_path / "csv" / "samples_dut.csv").open() as fh:
        assert next(csv.reader(fh)) == ["t_s", "x_ut", "y_ut", "z_ut", "t_unc_s"]
    time_base = json.loads((tmp_path / "csv" / "meta.json").read_text())["time_base"]
    assert time_base["start_monotonic_s"] == START_MONO
    assert time_base["start_time_utc"] == START_UTC


def test_hdf5_export_has_the_same_time_bases(tmp_path: Path) -> None:
    h5py = pytest.importorskip("h5py")
    folder = make_run(tmp_path / "runs", "SN-10")
    reader = RunReader(folder)
    path = export_hdf5(reader, tmp_path / "run.h5")
    files = export_csv(reader, tmp_path / "csv")
    reader.close()
    assert (tmp_path / "csv" / "samples_aligned.csv") in files
    with h5py.File(path) as f:
        assert f["samples/dut"].shape == (40, 4)  # as before
        np.testing.assert_allclose(f["time/samples/dut/t_run_s"][:3], [0.025, 0.125, 0.225])
        assert f["time/samples/reference/t_utc"][0].decode() == "2026-03-04T05:06:07.000Z"
        np.testing.assert_allclose(f["aligned/reference_x_ut"][:3], [0.25, 1.25, 2.25])
        assert f["aligned/t_utc"][1].decode() == "2026-03-04T05:06:07.125Z"
        assert json.loads(f.attrs["time_base"])["start_monotonic_s"] == START_MONO
