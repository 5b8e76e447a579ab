"""Issue 19: the blockwise (bounded-memory) fits give the in-memory answers; a wide telemetry set
(20 channels) still recovers the truth; the CSV reader's blocks join up; the calibrate command
loads no scipy, matplotlib or h5py. Speed and memory are measured by
bench/bench_calibrate_scale.py, not asserted here."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import rig.io.csv_table as csv_table
from rig.calibration import calibrate
from rig.calibration.batch.linear import (
    _telemetry_products,
    centered_fit,
    independent_from_gram,
)
from rig.calibration.batch.nonlinear import ml_fit, scalar_start
from rig.calibration.estimate import delta_method
from rig.calibration.residuals import (
    CHUNK_ROWS,
    p_from_calibration,
    p_from_theta,
    scalar_noise_gain,
    scalar_normal_equations,
    scalar_residuals,
    z_linear_design,
    z_observation,
)
from rig.calibration.solver import NormalEquations
from rig.calibration.synthetic import rax_like
from rig.errors import UserInputError
from rig.io.csv_table import read_columns, read_table, write_columns


@pytest.fixture(scope="module")
def long_case():  # type: ignore[no-untyped-def]
    """More samples than two blocks of the accumulating passes."""
    case = rax_like(2 * CHUNK_ROWS + 5000, seed=21)
    assert case.samples.n > 2 * CHUNK_ROWS
    return case


def test_blockwise_normal_equations_equal_the_whole_jacobian(long_case) -> None:  # type: ignore[no-untyped-def]
    s = long_case.samples
    p = p_from_calibration(long_case.truth, vector=False) * 1.01
    w = np.random.default_rng(3).uniform(0.5, 2.0, s.n)
    r_out = np.empty(s.n)
    ne = scalar_normal_equations(p, s, w, residuals_out=r_out)
    r, jac = scalar_residuals(p, s, np.sqrt(w))
    ref = NormalEquations.of(r, jac)
    np.testing.assert_allclose(ne.jtj, ref.jtj, rtol=1e-10)
    np.testing.assert_allclose(ne.jtr, ref.jtr, rtol=1e-9, atol=1e-9 * np.abs(ref.jtr).max())
    assert ne.cost == pytest.approx(ref.cost, rel=1e-11)
    assert ne.gain is not None
    np.testing.assert_allclose(ne.gain, scalar_noise_gain(p, s), rtol=1e-13)
    np.testing.assert_allclose(r_out, scalar_residuals(p, s)[0], rtol=1e-13, atol=1e-13)
    fisher = scalar_normal_equations(p, s, noise_weighted=True).jtj
    jf = scalar_residuals(p, s)[1] / ne.gain[:, None]
    np.testing.assert_allclose(fisher, jf.T @ jf, rtol=1e-10)


def _centered_by_svd(s):  # type: ignore[no-untyped-def]
    """The centered estimator as it was before issue 19: an SVD lstsq on the whole design."""
    lin = z_linear_design(s)
    prods = _telemetry_products(s.telemetry)
    prods = prods[:, independent_from_gram((prods - prods.mean(0)).T @ (prods - prods.mean(0)))]
    x = np.hstack([lin, prods])
    z = z_observation(s)
    w = 1.0 / (4.0 * s.field_magnitude_ut**2)
    wn = w / w.sum()
    sw = np.sqrt(w)
    xs, zs = (x - wn @ x) * sw[:, None], (z - wn @ z) * sw
    col = np.linalg.norm(xs, axis=0)
    b = np.linalg.lstsq(xs / col, zs, rcond=None)[0] / col
    resid = zs - xs @ b
    inv = np.linalg.inv((xs / col).T @ (xs / col)) / np.outer(col, col)
    n_theta = lin.shape[1]
    var = float(resid @ resid) / (s.n - x.shape[1] - 1)
    return delta_method(p_from_theta, b[:n_theta], var * inv[:n_theta, :n_theta], "svd")


def test_centered_normal_equations_match_the_svd_solution(long_case) -> None:  # type: ignore[no-untyped-def]
    s = long_case.samples
    est = centered_fit(s)
    p_ref, cov_ref = _centered_by_svd(s)
    sigma = np.sqrt(np.diag(cov_ref))
    assert np.max(np.abs(est.p - p_ref) / sigma) < 1e-6
    np.testing.assert_allclose(np.sqrt(np.diag(est.covariance)), sigma, rtol=1e-6)


def test_quick_start_is_labelled_and_leads_to_the_same_ml_fit() -> None:
    s = rax_like(50_000, seed=22).samples
    quick = scalar_start(s, quick=True)
    full = scalar_start(s)
    assert quick.method == "centered-start" and full.method == "centered"
    a, b = ml_fit(s, start=quick.p), ml_fit(s, start=full.p)
    assert np.max(np.abs(a.p - b.p) / np.sqrt(np.diag(b.covariance))) < 1e-2
    # --method centered reports the linear estimator on every sample, not the quick start
    assert calibrate(s, "centered").method == "centered"


def test_twenty_channels_recover_the_truth() -> None:
    case = rax_like(20_000, seed=23, channels=20)
    s = case.samples
    assert s.n_channels == 20
    result = calibrate(s)
    assert result.p.size == 69
    truth = p_from_calibration(case.truth, vector=False)
    z = np.abs(result.p - truth) / result.sigma
    assert np.max(z) < 4.5, np.max(z)
    assert np.sqrt(np.mean(z**2)) < 1.5


def test_pieces_of_a_series_join_up() -> None:
    whole = rax_like(3000, seed=24, channels=8)
    first = rax_like(1000, seed=24, channels=8)
    rest = rax_like(2000, seed=24, channels=8, start_s=1000.0)
    np.testing.assert_array_equal(np.vstack([first.samples.telemetry, rest.samples.telemetry]),
                                  whole.samples.telemetry)  # fmt: skip


def test_independent_columns_drop_exact_dependencies() -> None:
    rng = np.random.default_rng(5)
    a, b = rng.normal(size=500), rng.normal(size=500)
    binary = (rng.uniform(size=500) > 0.5).astype(float)
    x = np.column_stack([a, b, a + b, binary, binary**2, 2.0 * a, rng.normal(size=500)])
    assert independent_from_gram(x.T @ x).tolist() == [0, 1, 3, 6]


def test_table_blocks_join_up_and_errors_keep_their_line(tmp_path: Path, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    monkeypatch.setattr(csv_table, "BLOCK_BYTES", 64)  # many blocks, lines cut at block edges
    rng = np.random.default_rng(6)
    data = rng.normal(size=(300, 4))
    path = tmp_path / "t.csv"
    write_columns(path, {n: data[:, j] for j, n in enumerate("abcd")}, fmt="%.9f")
    text = path.read_text()
    lines = text.splitlines()
    lines.insert(50, "# a comment line")
    path.write_text("\ufeff" + "\n".join(lines) + "\n", encoding="utf-8")
    table = read_table(path, ["d", "b"])
    assert table.shape == (300, 2) and table[:, 0].flags.c_contiguous  # each column one run
    np.testing.assert_allclose(table, data[:, [3, 1]], atol=1e-9)
    cols = read_columns(path, ["a"])
    np.testing.assert_allclose(cols["a"], data[:, 0], atol=1e-9)
    good = lines[200]
    lines[200] = lines[200].replace(lines[200].split(",")[2], "nan", 1)
    lines[250] = "1,2,3,inf"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    with pytest.raises(
        UserInputError, match=r"line 201, column 'c': value is NaN or infinite \(2 such"
    ):
        read_table(path, ["a", "c", "d"])
    lines[200], lines[250] = good, "1,2,x,4"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    with pytest.raises(UserInputError, match="line 251, column 'c': 'x' is not a number"):
        read_table(path, ["a", "b", "c"])


def test_calibrate_command_imports_no_heavy_module(tmp_path: Path) -> None:
    s = rax_like(3000, seed=25).samples
    path = tmp_path / "d.csv"
    cols = {f"m{a}": s.measured_ut[:, i] for i, a in enumerate("xyz")}
    cols["b"] = s.field_magnitude_ut
    cols |= {ch: s.telemetry[:, j] for j, ch in enumerate(s.channels)}
    write_columns(path, cols)
    code = (
        "import sys\nfrom rig.cli import main\n"
        f"code = main(['-q', 'calibrate', {str(path)!r}, '--measured', 'mx,my,mz',"
        f" '--field-magnitude', 'b', '--telemetry', {','.join(s.channels)!r},"
        f" '--out', {str(tmp_path / 'r.json')!r}])\n"
        "heavy = sorted(m for m in sys.modules if m.split('.')[0] in"
        " ('scipy', 'matplotlib', 'h5py', 'filterpy', 'sqlite3', 'yaml'))\n"
        "print(code, heavy)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "0 []", out.stdout + out.stderr
