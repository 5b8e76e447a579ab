"""The cage characterization measures a sweep point again when it stands out from the fit (a door,
a passing vehicle, a late reading), and only then."""

from __future__ import annotations

from typing import cast

import numpy as np

from rig.cage.characterize import characterize, outlying_points, sweep_points
from rig.cage.controller import CageController

K_TRUE = np.array([[40.2, 0.85, -0.42], [0.61, 39.1, 0.37], [-0.28, 0.74, 41.3]])
B0_TRUE = np.array([19.6, 1.2, -44.8])
NOISE_UT = 0.0025  # the mean of a point's readings, as on the simulated cage


def sweep(rng: np.random.Generator, repeats: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    points = np.tile(sweep_points(1.0), (repeats, 1))
    times = 0.9 * np.arange(len(points))
    drift = 0.4e-3 * (times - times.mean())[:, None] * np.array([1.0, -0.5, 0.8])
    fields = points @ K_TRUE.T + B0_TRUE + drift + NOISE_UT * rng.standard_normal((len(points), 3))
    return points, fields, times


def test_noise_alone_is_rarely_measured_again() -> None:
    rng = np.random.default_rng(3)
    flagged = sum(bool(outlying_points(*sweep(rng))) for _ in range(2000))
    # 42 point-axes a sweep at about 3e-4 each (Student's t, 8 degrees of freedom, beyond 6)
    assert flagged < 60, flagged


def test_one_disturbed_point_is_found_wherever_it_is() -> None:
    rng = np.random.default_rng(4)
    for index in range(14):
        points, fields, times = sweep(rng)
        fields[index, int(rng.integers(3))] += 0.05  # 50 nT: 20 times a point's noise
        assert outlying_points(points, fields, times)[:1] == [index]


def test_too_few_degrees_of_freedom_judge_nothing() -> None:
    points, fields, times = sweep(np.random.default_rng(5))
    fields[3, 0] += 1.0
    assert outlying_points(points[:8], fields[:8], times[:8]) == []


class DisturbedCage:
    """A cage controller as the characterization uses it: the field is ``K I + B0`` plus noise, and
    the first reading of one set of currents carries a disturbance."""

    def __init__(self, disturbed: np.ndarray, by_ut: np.ndarray) -> None:
        self.rng = np.random.default_rng(6)
        self.currents = np.zeros(3)
        self.t_s = 0.0
        self.disturbed, self.by_ut = disturbed, by_ut
        self.measured: list[np.ndarray] = []

    def set_currents(self, currents_a: np.ndarray) -> None:
        self.currents = np.asarray(currents_a, float)
        self.t_s += 0.5

    def sleep(self, seconds: float) -> None:
        self.t_s += seconds

    def measure_ut(self, samples: int) -> np.ndarray:
        self.t_s += samples / 20
        self.measured.append(self.currents.copy())
        field = K_TRUE @ self.currents + B0_TRUE + NOISE_UT * self.rng.standard_normal(3)
        first = sum(np.array_equal(c, self.disturbed) for c in self.measured) == 1
        return field + (
            self.by_ut if first and np.array_equal(self.currents, self.disturbed) else 0
        )

    def instruments(self) -> dict[str, str]:
        return {"reference": "fake"}


def test_a_disturbed_point_is_measured_again_and_the_fit_recovers(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    import timebase

    cage = DisturbedCage(np.array([0.0, -1.0, 0.0]), np.array([0.0, 0.0, 0.08]))
    monkeypatch.setattr(timebase, "monotonic", lambda: cage.t_s)
    model = characterize(cast(CageController, cage), 1.0, samples=5)
    assert model.meta["remeasured_points"] == [5]  # (0, -1, 0) is the sweep's sixth point
    assert len(cage.measured) == 15
    z = (model.k_ut_per_a - K_TRUE) / model.k_sigma
    assert np.abs(z).max() < 4.5 and model.meta["residual_rms_nt"] < 5.0
