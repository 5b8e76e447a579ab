"""Hostile numbers are one-line errors (exit 2), never internal errors (issue 51): a CSV cell of
1e308 in ``rig calibrate`` (its squares overflowed inside the fit), a singular or ill-conditioned
nominal coil matrix in the rig configuration, NaN in the simulator configuration; and an unknown
simulator configuration key is refused with the nearest valid one instead of silently ignored."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from rig.calibration.synthetic import RAX_CHANNELS
from rig.cli import main
from rig.config import load_rig_config
from rig.errors import UserInputError
from sim.config import DEFAULT_CONFIG, SimConfigError, load_config
from tests.test_check_cage_model import RIG

RAX_ARGS = ["--measured", "mx_ut,my_ut,mz_ut", "--field-magnitude", "b_ut", "--telemetry",
            ",".join(RAX_CHANNELS), "--noise-nt", "100"]  # fmt: skip


def one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "internal error" not in err and "Traceback" not in err, err
    return lines[0]


@pytest.fixture(scope="module")
def rax_csv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("data") / "rax.csv"
    assert main(["-q", "example-data", str(path), "--samples", "1000", "--seed", "4"]) == 0
    return path


@pytest.mark.parametrize("column", ["mx_ut", "b_ut", "i_px"])
@pytest.mark.parametrize("value", ["1e308", "-1e99", "1e31"])
def test_a_huge_csv_cell_names_its_line_and_column(
    rax_csv: Path, tmp_path: Path, column: str, value: str
) -> None:
    """1e308 in mx_ut was 'internal error: LinAlgError: SVD did not converge', in b_ut a
    FloatingPointError, in a telemetry channel an eigenvalue LinAlgError."""
    lines = rax_csv.read_text().splitlines()
    j = lines[0].split(",").index(column)
    cells = lines[10].split(",")
    cells[j] = value
    lines[10] = ",".join(cells)
    path = tmp_path / "hostile.csv"
    path.write_text("\n".join(lines) + "\n")
    done = subprocess.run([sys.executable, "-m", "rig.cli", "calibrate", str(path), *RAX_ARGS],
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert done.returncode == 2, done.stderr
    err = one_line(done.stderr)
    assert f"{path} line 11, column '{column}': value {float(value):g} is beyond 1e+30" in err, err
    assert "--drop-invalid" in err


def test_drop_invalid_leaves_a_huge_row_out(rax_csv: Path, tmp_path: Path) -> None:
    lines = rax_csv.read_text().splitlines()
    cells = lines[10].split(",")
    cells[1] = "1e308"
    lines[10] = ",".join(cells)
    path = tmp_path / "hostile.csv"
    path.write_text("\n".join(lines) + "\n")
    out = tmp_path / "result.json"
    assert main(["-q", "calibrate", str(path), *RAX_ARGS, "--drop-invalid", "--out", str(out)]) == 0
    assert out.exists()


@pytest.mark.parametrize(("k", "what"), [
    ("[[40.0, 0.0, 0.0], [0.0, 40.0, 0.0], [0.0, 0.0, 0.0]]", "is singular"),
    ("[[40.0, 0.0, 0.0], [40.0, 0.0, 0.0], [0.0, 0.0, 40.0]]", "is singular"),
    ("[[40.0, 0.0, 0.0], [0.0, 40.0, 0.0], [0.0, 0.0, 1e-6]]", "has condition number 4e+07"),
])  # fmt: skip
def test_a_singular_nominal_coil_matrix_is_refused_at_load(
    tmp_path: Path, k: str, what: str, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = tmp_path / "rig.toml"
    good = "[[40.0, 0.0, 0.0], [0.0, 40.0, 0.0], [0.0, 0.0, 40.0]]"
    cfg.write_text(RIG.format(calibration="").replace(good, k))
    with pytest.raises(UserInputError) as caught:
        load_rig_config(cfg)
    message = str(caught.value)
    assert message.startswith(f"{cfg}: [cage].nominal_k_ut_per_a: {what} (at most 1e+06)"), message
    assert "e.g. [[40, 0, 0], [0, 40, 0], [0, 0, 40]]" in message
    proc = tmp_path / "p.yaml"
    proc.write_text("procedure: T\nsteps:\n  - set_field: {field_ut: [0, 0, 20], hold_s: 1}\n")
    assert main(["check", str(proc), "--rig", str(cfg)]) == 2
    assert "nominal_k_ut_per_a" in one_line(capsys.readouterr().err)


def sim_config(tmp_path: Path, old: str, new: str) -> Path:
    text = DEFAULT_CONFIG.read_text(encoding="utf-8")
    assert old in text
    path = tmp_path / "cage.toml"
    path.write_text(text.replace(old, new, 1), encoding="utf-8")
    return path


@pytest.mark.parametrize(("old", "new", "expect"), [
    ("noise_ut = 0.003", "noise_ut = nan", "ambient.noise_ut is nan: write a finite number"),
    ("hot_switch_limit_a = 0.05", "hot_switch_limit_a = inf", "cage.hot_switch_limit_a is inf"),
    ("k_per_w = 2.0", "k_per_w = -inf", "thermal.k_per_w is -inf"),
    ("resistance_ohm = [4.0, 4.2, 3.8]", "resistance_ohm = [4.0, nan, 3.8]",
     "cage.resistance_ohm[1] is nan"),
    ("[[magnetometers]]\n", "[[magnetometers]]\nposition_m = [0, 0, 1e400]\n",
     "magnetometers[0].position_m[2] is inf"),
    ("[ambient]\n", "[ambient]\nnoise_uT = 0.1\n", "ambient: unknown key 'noise_uT'; did you mean 'noise_ut'?"),
    ("[[magnetometers]]\n", "[[magnetometers]]\nofset_ut = [1, 2, 3]\n",
     "magnetometers[0]: unknown key 'ofset_ut'; did you mean 'offset_ut'?"),
    ("[[supplies]]\n", "[[supplies]]\nresistance_ohms = 4.0\n",
     "supplies[0]: unknown key 'resistance_ohms'; did you mean 'resistance_ohm'?"),
    ("[cage]\n", "sed = 3\n[cage]\n", "the top level: unknown key 'sed'; did you mean 'seed'?"),
])  # fmt: skip
def test_the_simulator_configuration_refuses_non_finite_numbers_and_unknown_keys(
    tmp_path: Path, old: str, new: str, expect: str
) -> None:
    path = sim_config(tmp_path, old, new)
    with pytest.raises(SimConfigError) as caught:
        load_config(path)
    assert str(caught.value).startswith(f"{path}: {expect}"), str(caught.value)
    assert "\n" not in str(caught.value)


def test_rig_sim_refuses_a_nan_in_one_line(tmp_path: Path) -> None:
    path = sim_config(tmp_path, "noise_ut = 0.003", "noise_ut = nan")
    done = subprocess.run([sys.executable, "-m", "rig.cli", "sim", "--config", str(path)],
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 2, done.stderr
    assert "ambient.noise_ut is nan" in one_line(done.stderr)
