"""`rig calibrate` end to end through the real command: result file contract and bad input."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rig.calibration.synthetic import RAX_CHANNELS, RAX_K_UT_PER_A, RAX_TRUTH
from rig.cli import main

RAX_ARGS = ["--measured", "mx_ut,my_ut,mz_ut", "--field-magnitude", "b_ut",
            "--telemetry", ",".join(RAX_CHANNELS)]  # fmt: skip
SPRINGMANN_KEYS = {"a", "b", "c", "x0_ut", "y0_ut", "z0_ut", "rho_deg", "phi_deg", "lambda_deg"}


def rig(*args: str) -> subprocess.CompletedProcess[str]:
    """Run the installed command line exactly as a user would."""
    return subprocess.run([sys.executable, "-m", "rig.cli", *args], capture_output=True, text=True)


@pytest.fixture(scope="module")
def rax_csv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("data") / "rax.csv"
    assert main(["-q", "example-data", str(path), "--samples", "3000", "--seed", "4"]) == 0
    return path


@pytest.fixture(scope="module")
def cage_csv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("data") / "cage.csv"
    assert main(["-q", "example-data", str(path), "--kind", "cage", "--samples", "1500",
                 "--noise-nt", "50"]) == 0  # fmt: skip
    return path


def test_scalar_result_file_contract(rax_csv: Path, tmp_path: Path) -> None:
    out = tmp_path / "result.json"
    proc = rig("calibrate", str(rax_csv), *RAX_ARGS, "--noise-nt", "100", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    assert "k[i_eps].z" in proc.stdout and "chi2/dof" in proc.stdout
    res = json.loads(out.read_text())
    assert res["model"] == "scalar" and res["method"] == "ml"
    assert res["samples"] == 3000 and res["channels"] == list(RAX_CHANNELS)
    assert set(res["springmann"]) == SPRINGMANN_KEYS
    assert set(res["sigma"]["springmann"]) == SPRINGMANN_KEYS
    assert set(res["sigma"]["k_ut_per_unit"]) == set(RAX_CHANNELS)
    assert np.shape(res["correction"]["matrix"]) == (3, 3)
    assert np.shape(res["crassidis"]["D"]) == (3, 3) and len(res["crassidis"]["b_ut"]) == 3
    for key in ("residual_rms_nt", "residual_mean_nt"):
        assert isinstance(res[key], float)
    assert set(res["crlb_ratio"]["springmann"]) == SPRINGMANN_KEYS
    # values against the truth that generated the file, within 4 sigma
    sp, sig = res["springmann"], res["sigma"]["springmann"]
    assert abs(sp["rho_deg"] - np.degrees(RAX_TRUTH.rho)) < 4 * sig["rho_deg"]
    assert abs(sp["y0_ut"] - RAX_TRUTH.y0) < 4 * sig["y0_ut"]
    k = np.array([res["correction"]["k_ut_per_unit"][c] for c in RAX_CHANNELS])
    ks = np.array([res["sigma"]["k_ut_per_unit"][c] for c in RAX_CHANNELS])
    assert np.all(np.abs(k - RAX_K_UT_PER_A) < 4 * ks)
    assert abs(res["residual_rms_nt"] / 100.0 - 1) < 0.1


def test_corrected_field_formula_from_the_json(rax_csv: Path, tmp_path: Path) -> None:
    """The contract: corrected field = matrix @ (m - offset_ut - sum_j k_j u_j)."""
    out = tmp_path / "r.json"
    assert main(["-q", "calibrate", str(rax_csv), *RAX_ARGS, "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    data = np.genfromtxt(rax_csv, delimiter=",", names=True)
    m = np.column_stack([data["mx_ut"], data["my_ut"], data["mz_ut"]])
    bias = np.array(res["correction"]["offset_ut"]) + sum(
        np.outer(data[c], res["correction"]["k_ut_per_unit"][c]) for c in RAX_CHANNELS
    )
    h = (m - bias) @ np.array(res["correction"]["matrix"]).T
    err_nt = 1000 * (np.linalg.norm(h, axis=1) - data["b_ut"])
    assert abs(np.sqrt(np.mean(err_nt**2)) - res["residual_rms_nt"]) < 1e-3


def test_vector_result_and_methods(cage_csv: Path, tmp_path: Path) -> None:
    out = tmp_path / "v.json"
    args = ["calibrate", str(cage_csv), "--measured", "mx_ut,my_ut,mz_ut",
            "--field", "hx_ut,hy_ut,hz_ut", "--telemetry", "load1_a,load2_a"]  # fmt: skip
    assert main(["-q", *args, "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["model"] == "vector" and res["method"] == "vector"
    assert res["mounting"]["observable"] is True
    np.testing.assert_allclose(res["mounting"]["rotation_vector_deg"], [1.5, -2.0, 3.0], atol=0.05)
    for method in ("ml", "twostep", "centered", "ellipsoid"):
        assert main(["-q", *args, "--method", method, "--out", str(out)]) == 0
        res = json.loads(out.read_text())
        assert res["model"] == "scalar" and res["method"] == method


def test_c_header_compiles_and_matches_apply(rax_csv: Path, tmp_path: Path) -> None:
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler")
    header = tmp_path / "magcal.h"
    out = tmp_path / "r.json"
    assert main(["-q", "calibrate", str(rax_csv), *RAX_ARGS, "--out", str(out),
                 "--c-header", str(header)]) == 0  # fmt: skip
    (tmp_path / "t.c").write_text(
        '#include <stdio.h>\n#include "magcal.h"\n'
        "int main(void) {\n"
        "  const float m[3] = {12.5f, -30.25f, 8.0f};\n"
        "  const float u[5] = {0.1f, 0.0f, 0.4f, 0.0f, 1.55f};\n"
        "  float h[3];\n  magcal_apply(m, u, h);\n"
        '  printf("%.6f %.6f %.6f\\n", h[0], h[1], h[2]);\n  return 0;\n}\n'
    )
    subprocess.run([cc, "-std=c99", "-Wall", "-Werror", "-o", str(tmp_path / "t"),
                    str(tmp_path / "t.c")], check=True)  # fmt: skip
    got = np.array(subprocess.run([str(tmp_path / "t")], capture_output=True, text=True,
                                  check=True).stdout.split(), float)  # fmt: skip
    res = json.loads(out.read_text())
    corr = res["correction"]
    u = np.array([0.1, 0.0, 0.4, 0.0, 1.55])
    bias = np.array(corr["offset_ut"]) + u @ np.array(
        [corr["k_ut_per_unit"][c] for c in RAX_CHANNELS]
    )
    want = np.array(corr["matrix"]) @ (np.array([12.5, -30.25, 8.0]) - bias)
    np.testing.assert_allclose(got, want, atol=2e-4)


def _one_line_error(proc: subprocess.CompletedProcess[str], *fragments: str) -> None:
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "Traceback" not in proc.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


def test_missing_file(tmp_path: Path) -> None:
    _one_line_error(rig("calibrate", str(tmp_path / "nope.csv"), *RAX_ARGS), "no such file")


def test_missing_column_suggests_close_name(rax_csv: Path) -> None:
    proc = rig("calibrate", str(rax_csv), "--measured", "mx_ut,my_ut,mzz_ut",
               "--field-magnitude", "b_ut")  # fmt: skip
    _one_line_error(proc, "no column 'mzz_ut'", "did you mean 'mz_ut'")


def _damaged(rax_csv: Path, tmp_path: Path, line_no: int, col: int, value: str) -> Path:
    lines = rax_csv.read_text().splitlines()
    cells = lines[line_no - 1].split(",")
    cells[col] = value
    lines[line_no - 1] = ",".join(cells)
    path = tmp_path / "bad.csv"
    path.write_text("\n".join(lines) + "\n")
    return path


def test_non_numeric_cell(rax_csv: Path, tmp_path: Path) -> None:
    path = _damaged(rax_csv, tmp_path, 57, 2, "abc")
    _one_line_error(
        rig("calibrate", str(path), *RAX_ARGS), "line 57", "'my_ut'", "'abc' is not a number"
    )


def test_empty_cell(rax_csv: Path, tmp_path: Path) -> None:
    path = _damaged(rax_csv, tmp_path, 10, 4, "")
    _one_line_error(rig("calibrate", str(path), *RAX_ARGS), "line 10", "'b_ut'", "empty")


def test_nan_row(rax_csv: Path, tmp_path: Path) -> None:
    path = _damaged(rax_csv, tmp_path, 200, 1, "nan")
    _one_line_error(rig("calibrate", str(path), *RAX_ARGS), "line 200", "'mx_ut'", "NaN")


def test_too_few_samples(rax_csv: Path, tmp_path: Path) -> None:
    path = tmp_path / "short.csv"
    path.write_text("\n".join(rax_csv.read_text().splitlines()[:21]) + "\n")
    _one_line_error(rig("calibrate", str(path), *RAX_ARGS), "only 20 samples", "at least")


def test_identical_telemetry_channels(rax_csv: Path, tmp_path: Path) -> None:
    lines = rax_csv.read_text().splitlines()
    path = tmp_path / "dup.csv"
    path.write_text(
        "\n".join(f"{ln},{ln.split(',')[5] if i else 'copy'}" for i, ln in enumerate(lines)) + "\n"
    )
    proc = rig("calibrate", str(path), "--measured", "mx_ut,my_ut,mz_ut", "--field-magnitude",
               "b_ut", "--telemetry", "i_px,copy")  # fmt: skip
    _one_line_error(proc, "linearly dependent", "'i_px'", "'copy'", "drop one")


def test_zero_field_magnitude(rax_csv: Path, tmp_path: Path) -> None:
    path = _damaged(rax_csv, tmp_path, 30, 4, "0")
    _one_line_error(rig("calibrate", str(path), *RAX_ARGS), "zero", "|h| > 0")


def test_constant_field_with_centered(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    d = rng.standard_normal((500, 3))
    m = 45.0 * d / np.linalg.norm(d, axis=1)[:, None] + 2.0 + 0.05 * rng.standard_normal((500, 3))
    path = tmp_path / "const.csv"
    np.savetxt(path, np.column_stack([m, np.full(500, 45.0)]), delimiter=",",
               header="mx,my,mz,b", comments="")  # fmt: skip
    proc = rig("calibrate", str(path), "--measured", "mx,my,mz", "--field-magnitude", "b",
               "--method", "centered")  # fmt: skip
    _one_line_error(proc, "nearly constant", "--method ml")
    ok = rig("calibrate", str(path), "--measured", "mx,my,mz", "--field-magnitude", "b")
    assert ok.returncode == 0, ok.stderr


def test_usage_errors_exit_2(rax_csv: Path) -> None:
    _one_line_error(rig("calibrate", str(rax_csv), "--measured", "mx_ut,my_ut"), "--field")
    proc = rig("calibrate", str(rax_csv), "--measured", "mx_ut,my_ut", "--field-magnitude", "b_ut")
    _one_line_error(proc, "--measured needs three columns")
    proc = rig("calibrate", str(rax_csv), *RAX_ARGS, "--method", "vector")
    _one_line_error(proc, "--method vector needs the field vector")
    proc = rig("calibrate", str(rax_csv), *RAX_ARGS, "--noise-nt", "-3")
    _one_line_error(proc, "--noise-nt must be positive")
    proc = rig("calibrate", str(rax_csv), *RAX_ARGS, "--robust", "huber", "--method", "centered")
    _one_line_error(proc, "--robust works with")


def test_help_and_version() -> None:
    assert rig("--help").returncode == 0
    assert "--field-magnitude" in rig("calibrate", "--help").stdout
    assert rig("--version").stdout.startswith("rig ")


def test_quiet_prints_nothing(rax_csv: Path) -> None:
    proc = rig("-q", "calibrate", str(rax_csv), *RAX_ARGS)
    assert proc.returncode == 0 and proc.stdout == ""


def test_filter_method_result_and_history(rax_csv: Path, tmp_path: Path) -> None:
    """--method ekf: the batch result-file contract plus a filter block; --history converges."""
    out, hist = tmp_path / "ekf.json", tmp_path / "hist.csv"
    proc = rig("calibrate", str(rax_csv), *RAX_ARGS, "--noise-nt", "100", "--method", "ekf",
               "--out", str(out), "--history", str(hist))  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    res = json.loads(out.read_text())
    assert res["method"] == "ekf" and set(res["springmann"]) == SPRINGMANN_KEYS
    assert {"b_ut", "D", "b_sigma_ut", "D_sigma"} <= set(res["crassidis"])
    assert 0.8 < res["filter"]["mean_nis"] < 1.3
    sp, sig = res["springmann"], res["sigma"]["springmann"]
    assert abs(sp["y0_ut"] - RAX_TRUTH.y0) < 4 * sig["y0_ut"]
    rows = np.genfromtxt(hist, delimiter=",", names=True)
    assert rows["sample"][-1] == 3000 and rows.size > 100
    assert rows["sigma_a"][-1] < 0.1 * rows["sigma_a"][len(rows) // 10]  # sigma shrinks
    proc = rig("calibrate", str(rax_csv), *RAX_ARGS, "--history", str(hist))
    _one_line_error(proc, "--history needs a filter")


def test_method_choices_come_from_the_estimator_table() -> None:
    import argparse

    from rig.calibration.estimators import method_names, spoken
    from rig.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    method = next(a for a in sub.choices["calibrate"]._actions if a.dest == "method")
    assert tuple(method.choices or ()) == method_names()
    sequential = spoken(method_names(kind="sequential"), "and")  # the registry's, in its order
    assert f"{sequential} are the sequential" in (method.help or "")
    assert set(method_names(kind="sequential")) >= {"centered-seq", "ekf", "ukf", "rls"}


def test_cage_set_field_help_and_usage_error() -> None:
    """set-field's three field components: its help and usage errors are text, not a traceback."""
    proc = rig("cage", "set-field", "--help")
    assert proc.returncode == 0 and "BX BY BZ" in proc.stdout and "field z in uT" in proc.stdout
    proc = rig("cage", "set-field", "1", "2")
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "BZ" in proc.stderr


def test_devices_scan_is_registered_and_loaded_only_when_used() -> None:
    proc = rig("devices", "scan", "--help")
    assert proc.returncode == 0 and "--port PATH" in proc.stdout and "--write FILE" in proc.stdout
    assert "devices" in rig("--help").stdout
    proc = rig("devices", "scan", "--bogus")
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1
    code = (
        "import sys; from rig.cli import build_parser; build_parser().parse_args(['runs']);"
        " sys.exit(bool({'rig.bringup', 'numpy', 'pymodbus'} & set(sys.modules)))"
    )
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_every_option_of_every_command_has_help() -> None:
    """`--help` explains every argument (issue 33: --runs-dir, PROCEDURE, --set, ... had none)."""
    import argparse

    from rig.cli import build_parser

    def walk(p: argparse.ArgumentParser, path: list[str]) -> list[str]:
        bare = []
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for name, sp in a.choices.items():
                    bare += walk(sp, [*path, name])
            elif not isinstance(a, argparse._HelpAction) and not a.help:
                bare.append(" ".join([*path, "/".join(a.option_strings) or a.dest]))
        return bare

    assert walk(build_parser(), ["rig"]) == []


def test_rig_cage_takes_rig_like_every_other_command() -> None:
    from rig.cli import build_parser

    for spelling in ("--rig", "--rig-config"):  # the old spelling stays an alias
        args = build_parser().parse_args(["cage", "set-field", "0", "0", "0", spelling, "r.toml"])
        assert str(args.rig_config) == "r.toml"
