"""Monte Carlo audit of the reported uncertainty: does |error| / sigma behave as promised?

Each scenario of :data:`SCENARIOS` names how its data are made (a generator of
:mod:`rig.calibration.synthetic`, without noise), the noise added per draw (its colour and tails)
and the ``calibrate`` options it is fitted with, exactly as ``rig calibrate`` fits (same entry
point). A draw adds new noise (and, for the delay scenarios, draws new currents and true delays)
and returns ``(estimate - truth) / sigma`` per parameter, the profiled ones (delays, the scale per
kelvin) included. Honest sigmas give an rms of 1 and about 5 % of draws beyond 1.96. Used by
``tests/test_uncertainty_audit.py`` and ``bench/bench_uncertainty_audit.py`` (which runs the draws
on Dask; ADR 0025).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from rig.calibration.params import Array
from rig.calibration.residuals import Samples, p_from_calibration
from rig.calibration.synthetic import (
    SyntheticCase,
    cage_like,
    constant_field_cap,
    delayed_currents,
    thermal_soak,
    trmm_like,
)
from rig.errors import CalibrationError

Data = Literal[
    "cage sweep", "cage sweep, |h| only", "TRMM orbit", "hemisphere", "smooth currents",
    "steps at random times", "steps on the sample grid", "thermal soak",
]  # fmt: skip
"""How a scenario's data are made (see :func:`make_case`)."""

OrbitField = Callable[[float, float, Array], Array]
"""The body-frame field (uT, (N, 3)) of an Earth-pointing circular orbit at an altitude (km) and
inclination (deg), at times (s) from its start. The orbit geometry and IGRF live above the
calibration core (``rig.steps.orbit.circular_orbit_track``): the caller passes it."""

TRMM_ALTITUDE_KM = 402.0
TRMM_INCLINATION_DEG = 35.0
TRMM_TIMES_S = np.arange(0.0, 8 * 3600.0, 10.0)
"""Crassidis, Lai and Harman's orbit: a sample every 10 s for 8 h (2880 samples)."""
MAX_DELAY_S = 1.0
"""The delay scenarios' search range (``max_delay_s``); their true delays are drawn within
``+-TRUE_DELAY_SPAN_S`` per draw."""
TRUE_DELAY_SPAN_S = 0.4


@dataclass(frozen=True)
class Scenario:
    """How the data are made (``data``, ``samples``), the raw noise per axis (marginal 1-sigma
    ``noise_ut``; AR(1) with correlation time ``tau`` samples, 0: white; Gaussian, or Student t
    with ``dof`` degrees of freedom scaled to that sigma) and the ``calibrate`` options: ``method``,
    ``delays`` (every load channel's delay, with the sample times), ``temperature``."""

    name: str
    data: Data = "cage sweep"
    method: Literal["vector", "ml", "twostep", "ekf", "ukf"] = "vector"
    tau: float = 0.0
    dof: float | None = None
    noise_ut: float = 0.05
    samples: int = 2000
    delays: bool = False
    temperature: bool = False

    @property
    def fresh_data(self) -> bool:
        """Whether each draw makes its own data (new currents and true delays), not only noise:
        where the step times and the delays' place on the sample grid matter to the error."""
        return self.delays


SCENARIOS = (
    Scenario("white"),
    Scenario("AR(1) tau 1", tau=1.0),
    Scenario("AR(1) tau 3", tau=3.0),
    Scenario("AR(1) tau 10", tau=10.0),
    Scenario("AR(1) tau 30", tau=30.0),
    Scenario("Student t, 3 dof", dof=3.0),
    Scenario("scalar fit with telemetry", "cage sweep, |h| only", "ml"),
    Scenario("TRMM orbit", "TRMM orbit", "ml", samples=TRMM_TIMES_S.size),
    Scenario("TRMM orbit, twostep", "TRMM orbit", "twostep", samples=TRMM_TIMES_S.size),
    Scenario("TRMM orbit, ekf", "TRMM orbit", "ekf", samples=TRMM_TIMES_S.size),
    Scenario("TRMM orbit, ukf", "TRMM orbit", "ukf", samples=TRMM_TIMES_S.size),
    Scenario("one-sided (hemisphere)", "hemisphere", "ml", noise_ut=0.2, samples=5000),
    Scenario("delays, smooth currents", "smooth currents", samples=1200, delays=True),
    Scenario("delays, steps at random times", "steps at random times", samples=2000, delays=True),
    Scenario("delays, steps on the grid", "steps on the sample grid", samples=2000, delays=True),
    Scenario("temperature", "thermal soak", samples=4000, temperature=True),
)
"""The audit's scenarios: the vector fit under white, coloured (several correlation times) and
heavy-tailed noise; a scalar (``ml``) fit with two load channels; the TRMM orbit (Crassidis et
al.); a uniform hemisphere of a constant field (fitted with a warning, docs/adr/0026); telemetry
delays with smooth currents and with step currents (at random times, and on the sample grid as
in a CSV whose currents were switched in step with the DUT); temperature coefficients."""


def scenario(name: str) -> Scenario:
    """The scenario called ``name``."""
    for sc in SCENARIOS:
        if sc.name == name:
            return sc
    raise KeyError(f"no audit scenario {name!r}: {[sc.name for sc in SCENARIOS]}")


def make_case(sc: Scenario, seed: int = 0, orbit_field: OrbitField | None = None) -> SyntheticCase:
    """Scenario ``sc``'s data without noise (seeded); the TRMM orbit needs ``orbit_field``."""
    n = sc.samples
    if sc.data in ("cage sweep", "cage sweep, |h| only"):
        return cage_like(n, seed=seed, noise_ut=0.0)
    if sc.data == "TRMM orbit":
        if orbit_field is None:
            raise ValueError("the TRMM orbit scenario needs orbit_field (rig.steps.orbit)")
        field = orbit_field(TRMM_ALTITUDE_KM, TRMM_INCLINATION_DEG, TRMM_TIMES_S[:n])
        return trmm_like(field, noise_ut=0.0)
    if sc.data == "hemisphere":
        return constant_field_cap(90.0, n, noise_ut=0.0, seed=seed)
    if sc.data == "thermal soak":
        return thermal_soak(n, seed=seed, noise_ut=0.0)
    rng = np.random.default_rng([seed, 35])
    first, second = (float(d) for d in rng.uniform(-TRUE_DELAY_SPAN_S, TRUE_DELAY_SPAN_S, 2))
    currents = "smooth" if sc.data == "smooth currents" else sc.data
    return delayed_currents(n, seed=seed, noise_ut=0.0, currents=currents,
                            delays_s=(first, second))  # fmt: skip


def coloured_noise(rng: np.random.Generator, shape: tuple[int, int], sc: Scenario) -> Array:
    """Noise (N, 3) uT of scenario ``sc``: innovations (Gaussian or Student t, unit variance)
    filtered by AR(1) ``x_k = rho x_(k-1) + sqrt(1 - rho^2) e_k``, ``rho = exp(-1 / tau)``."""
    if sc.dof is None:
        e = rng.standard_normal(shape)
    else:
        e = rng.standard_t(sc.dof, size=shape) / math.sqrt(sc.dof / (sc.dof - 2.0))
    if sc.tau > 0:
        rho = math.exp(-1.0 / sc.tau)
        gain = math.sqrt(1.0 - rho * rho)
        for k in range(1, shape[0]):
            e[k] = rho * e[k - 1] + gain * e[k]
    return sc.noise_ut * e


def noisy_draw(
    case: SyntheticCase | None, sc: Scenario, seed: int
) -> tuple[SyntheticCase, Samples]:
    """Draw ``seed`` of scenario ``sc``: its case (``case``, or its own from ``seed`` for a
    scenario with ``fresh_data``) and the samples with the draw's noise (no field vector for a
    scalar fit)."""
    if sc.fresh_data or case is None:
        case = make_case(sc, seed)
    s = case.samples
    rng = np.random.default_rng([seed, 34])
    m = s.measured_ut + coloured_noise(rng, (s.n, 3), sc)
    field = s.field_ut if sc.method == "vector" else None
    return case, Samples(m, s.field_magnitude_ut, s.telemetry, s.channels, field)


def timed(sc: Scenario) -> bool:
    """Whether scenario ``sc`` is fitted with its sample times (as a CSV's time column gives
    them): delays, and the filters."""
    return sc.delays or sc.method in ("ekf", "ukf")


def draw_z(case: SyntheticCase | None, sc: Scenario, seed: int) -> tuple[tuple[str, ...], Array]:
    """Parameter names and ``(estimate - truth) / reported sigma`` of one draw: new noise on
    ``case`` (None, or any case, for a scenario with ``fresh_data``: its own data from ``seed``)."""
    from rig.calibration.fit import calibrate

    case, noisy = noisy_draw(case, sc, seed)
    s = case.samples
    vector = sc.method == "vector"
    result = calibrate(noisy, sc.method, times_s=case.time_s if timed(sc) else None,
                       delays=s.channels if sc.delays else (), max_delay_s=MAX_DELAY_S,
                       temperature=case.temperature if sc.temperature else None)  # fmt: skip
    error = result.p - p_from_calibration(case.truth, vector=vector)
    if vector:
        # the rotation error angles refer to the fitted mounting: compare rotations, not vectors
        error[9:12] = _rotation_error(result.calibration.rotation, case.truth.rotation)
    names, z = result.names, error / result.sigma
    if result.profiled is not None:
        fit, truth = result.profiled, dict(case.profiled_truth)
        labels = tuple(prm.table_label for prm in fit.params)
        names += labels
        z = np.concatenate([z, (fit.values - [truth[k] for k in labels]) / fit.sigma])
    return names, z


def _rotation_error(fitted: Array, truth: Array) -> Array:
    """Small rotation vector (rad) taking ``truth`` to ``fitted``, about the DUT axes."""
    d = fitted @ truth.T
    return np.array([d[2, 1] - d[1, 2], d[0, 2] - d[2, 0], d[1, 0] - d[0, 1]]) / 2.0


Draw = Callable[[SyntheticCase | None, Scenario, int], tuple[tuple[str, ...], Array]]
"""One draw: names and ``(estimate - truth) / sigma`` (:func:`draw_z`, or the bench's CLI draw)."""


def draw_chunk(
    case: SyntheticCase | None, sc: Scenario, seeds: Sequence[int], draw: Draw = draw_z
) -> tuple[tuple[str, ...], Array]:
    """Names and ``z`` (len(seeds), P) of the draws ``seeds`` of scenario ``sc`` on ``case``
    (None for a scenario with ``fresh_data``) by ``draw`` (default :func:`draw_z`): one task of
    the bench's Dask run. A draw that ``calibrate`` refuses (a CalibrationError: e.g. a one-sided
    fit whose noise bias reaches three sigma) is a row of NaN; all refused: no names, shape
    (len(seeds), 0)."""
    rows: list[tuple[tuple[str, ...], Array] | None] = []
    for k in seeds:
        try:
            rows.append(draw(case, sc, k))
        except CalibrationError:
            rows.append(None)
    done = [row for row in rows if row is not None]
    names = done[0][0] if done else ()
    blank = np.full(len(names), np.nan)
    return names, np.array([blank if row is None else row[1] for row in rows]).reshape(
        len(rows), len(names)
    )


def audit(
    sc: Scenario, draws: int, *, seed: int = 0, orbit_field: OrbitField | None = None
) -> tuple[tuple[str, ...], Array]:
    """Names and ``z`` (draws, P) of ``draws`` draws of scenario ``sc``, one after another in
    this process (draw ``k`` uses seed ``k``; the bench runs the same draws on Dask)."""
    case = None if sc.fresh_data else make_case(sc, seed, orbit_field)
    return draw_chunk(case, sc, range(draws))


def summary(z: Array) -> tuple[Array, Array, Array]:
    """Per parameter: rms of ``z``, 95th percentile of ``|z|``, fraction of ``|z| > 4``, over
    the draws that were fitted (refused ones, rows of NaN, left out)."""
    z = z[~np.all(np.isnan(z), axis=1)]
    return (np.sqrt(np.mean(z**2, axis=0)), np.percentile(np.abs(z), 95, axis=0),
            np.mean(np.abs(z) > 4.0, axis=0))  # fmt: skip


def refused(z: Array) -> int:
    """How many draws ``calibrate`` refused (rows of NaN)."""
    return int(np.sum(np.all(np.isnan(z), axis=1))) if z.shape[1] else z.shape[0]
