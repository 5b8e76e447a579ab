"""`rig check --rig` judges coil currents with what the rig knows of its cage (issue 30): the last
characterization with its 3-sigma uncertainty, or, with none yet, an ambient field that a
characterization step inside the procedure will measure and the currents will then cancel."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rig.cage.model import SCHEMA
from rig.cli import main
from rig.procedure.plan import EARTH_MAX_UT, CageModelUncertainty, current_margin_a

RIG = """
[cage]
axes = {{ x = "coil_x", y = "coil_y", z = "coil_z" }}
max_current_a = [2.5, 2.5, 2.5]
max_field_ut = 120.0
max_slew_a_per_s = 10.0
nominal_k_ut_per_a = [[40.0, 0.0, 0.0], [0.0, 40.0, 0.0], [0.0, 0.0, 40.0]]
{calibration}
""" + "".join(
    f'\n[devices.{n}]\nkind = "riden-rd60xx"\nprotocol = "modbus-tcp"\nhost = "127.0.0.1"\nport = {9 + i}\n'
    for i, n in enumerate(("coil_x", "coil_y", "coil_z"))
)
CHARACTERIZE = "  - characterize_cage: {amplitude_a: 1.0, samples: 10, repeats: 1}\n"
HOLD_Z_80 = "  - set_field: {field_ut: [0, 0, 80], hold_s: 1}\n"  # 2.0 A on z with no ambient


def write(
    tmp_path: Path, steps: str, calibration: dict[str, object] | None = None
) -> tuple[Path, Path]:
    proc = tmp_path / "p.yaml"
    proc.write_text("procedure: T\nsteps:\n" + steps)
    line = ""
    if calibration is not None:
        (tmp_path / "cage.json").write_text(json.dumps({"schema": SCHEMA, **calibration}))
        line = f'calibration = "{tmp_path / "cage.json"}"'
    cfg = tmp_path / "rig.toml"
    cfg.write_text(RIG.format(calibration=line))
    return proc, cfg


def test_margins_follow_the_model_and_the_unknown_ambient() -> None:
    k = 40.0 * np.eye(3)
    model, ambient = current_margin_a(k, [1.0, 0.0, 2.0], CageModelUncertainty(
        k_sigma=np.full((3, 3), 0.1), b0_sigma_ut=np.array([0.5, 0.5, 0.5])))  # fmt: skip
    # 3 * (0.5 + 0.1 * (1 + 0 + 2)) / 40 per axis
    assert model == pytest.approx(np.full(3, 3 * 0.8 / 40))
    assert ambient == pytest.approx(np.zeros(3))
    _, ambient = current_margin_a(
        k, [0, 0, 0], CageModelUncertainty(unknown_ambient_ut=EARTH_MAX_UT)
    )
    assert ambient == pytest.approx(np.full(3, EARTH_MAX_UT / 40))


def test_no_characterization_yet_puts_late_fields_at_risk(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # before the characterization the lab field adds to the field: 50 + 66 uT within 120 uT
    proc, cfg = write(tmp_path, HOLD_Z_80.replace("80", "50") + CHARACTERIZE + HOLD_Z_80)
    assert main(["check", str(proc), "--rig", str(cfg)]) == 0  # within the limits as known
    out = capsys.readouterr().out
    assert "cage model: nominal_k_ut_per_a: no cage characterization yet" in out
    risks = [line for line in out.splitlines() if line.startswith("AT RISK:")]
    # only the field after the characterization: before it the currents ignore the ambient
    assert len(risks) == 1 and "p.yaml:5: step 3" in risks[0] and "axis z" in risks[0]
    assert f"ambient field of up to {EARTH_MAX_UT:g} uT" in risks[0] and "up to 3.65 A" in risks[0]
    assert "AT RISK (above)" in out


def test_a_characterization_with_its_uncertainty_decides(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cal = {"k_ut_per_a": (40.0 * np.eye(3)).tolist(), "b0_ut": [19.6, 1.2, -16.0],
           "k_sigma_ut_per_a": np.zeros((3, 3)).tolist(), "b0_sigma_ut": [0.0, 0.0, 0.0],
           "date": "2026-11-25T10:00:00+00:00"}  # fmt: skip
    proc, cfg = write(tmp_path, HOLD_Z_80, cal)
    # (80 + 16) / 40 = 2.4 A: inside 2.5 A with an exact model
    assert main(["check", str(proc), "--rig", str(cfg)]) == 0
    out = capsys.readouterr().out
    assert "the cage characterization of 2026-11-25T10:00:00+00:00" in out and "z 2.400 A" in out
    # the same characterization known to 1.5 uT on z: 2.4 + 3 * 1.5 / 40 = 2.51 A > 2.5 A
    cal["b0_sigma_ut"] = [0.0, 0.0, 1.5]
    proc, cfg = write(tmp_path, HOLD_Z_80, cal)
    assert main(["check", str(proc), "--rig", str(cfg)]) == 1
    out = capsys.readouterr().out
    assert "LIMIT:" in out and "+-0.11 A at 3 sigma of the cage model" in out
    assert "z 2.400 +-0.113 A" in out


def test_an_old_characterization_is_flagged_not_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import datetime as dt

    cal = {"k_ut_per_a": (40.0 * np.eye(3)).tolist(), "b0_ut": [0.0, 0.0, 0.0],
           "k_sigma_ut_per_a": np.zeros((3, 3)).tolist(), "b0_sigma_ut": [0.0, 0.0, 0.0],
           "date": "2025-01-10T10:00:00+00:00"}  # fmt: skip
    proc, cfg = write(tmp_path, HOLD_Z_80, cal)
    assert main(["check", str(proc), "--rig", str(cfg)]) == 0  # a warning, not a refusal
    warning = [line for line in capsys.readouterr().out.splitlines() if line.startswith("WARNING")]
    assert len(warning) == 1 and "the cage model of 2025-01-10 is" in warning[0]
    assert "calibration_valid_days = 90" in warning[0] and "cage-characterization" in warning[0]
    # a lab that trusts its cage for two years, or a fresh characterization: no warning
    cfg.write_text(cfg.read_text().replace("[cage]\n", "[cage]\ncalibration_valid_days = 730\n"))
    assert main(["check", str(proc), "--rig", str(cfg)]) == 0
    assert "WARNING" not in capsys.readouterr().out
    cal["date"] = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    proc, cfg = write(tmp_path, HOLD_Z_80, cal)
    assert main(["check", str(proc), "--rig", str(cfg)]) == 0
    assert "WARNING" not in capsys.readouterr().out
    del cal["date"]
    proc, cfg = write(tmp_path, HOLD_Z_80, cal)
    main(["check", str(proc), "--rig", str(cfg)])
    assert "has no date: characterize the cage" in capsys.readouterr().out


def test_an_old_metrology_result_in_the_record_is_flagged(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A fresh characterization with a field map of two years ago: rig check names the map and
    the procedure that measures it again."""
    import datetime as dt

    now = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
    cal = {"k_ut_per_a": (40.0 * np.eye(3)).tolist(), "b0_ut": [0.0, 0.0, 0.0], "date": now,
           "metrology": {"field_map": {"date": "2024-11-01T09:00:00+00:00", "run": "r1"},
                         "coil_axes": {"date": now, "run": "r2"}}}  # fmt: skip
    proc, cfg = write(tmp_path, HOLD_Z_80, cal)
    assert main(["check", str(proc), "--rig", str(cfg)]) == 0
    warning = [line for line in capsys.readouterr().out.splitlines() if line.startswith("WARNING")]
    assert len(warning) == 1 and "its field map result of 2024-11-01 is" in warning[0], warning
    assert "rig run cage-field-map" in warning[0] and "coil axes" not in warning[0]


def test_a_metrology_result_saves_a_new_version_and_keeps_the_old(tmp_path: Path) -> None:
    """Each result added to the cage record is a new dated version file; the record's path points
    at the newest; no version is overwritten, even two within one second."""
    from rig.cage.model import CageModel

    path = tmp_path / "cage.json"
    model = CageModel(40.0 * np.eye(3), np.zeros(3), meta={"date": "2026-11-01T10:00:00+00:00"})
    first = model.save(path)
    entry = {"date": "2026-11-20T08:00:00+00:00", "run": "run-7", "result": {"x": 1.0}}
    updated = model.with_metrology("field_map", entry)
    second, third = updated.save(path), updated.save(path)
    assert first.name == "cage.20261101T100000.json" and second.name == "cage.20261120T080000.json"
    assert third.name == "cage.20261120T080000-2.json"
    loaded = CageModel.load(path)
    assert loaded.metrology()["field_map"]["run"] == "run-7" and loaded.meta["date"].startswith(
        "2026-11-01"
    )
    assert "metrology" not in CageModel.load(first).meta
