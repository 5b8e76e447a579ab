"""The uncertainty budget of a DUT calibration: its statistical sigma and the cage's terms.

A calibration takes the reference's field as the truth at the DUT. Every cage term is an error of
that field: the reference's certificate (scale, axis angles, mounting), the field's change between
the reference's place and the DUT's (homogeneity), the lab field's difference between the two
places. Each is stated at +1 sigma as an affine map of the field, ``h -> h + E h + b``
(:class:`FieldTerm`; ``E`` dimensionless, ``b`` in uT), independent of the others. Its
contribution to the parameters is found by refitting the same data with the field so perturbed
(GUM 5.1.2, linear propagation with the sensitivity found numerically: the estimator is the
function, refitted once per term): ``c_k = v(h + E_k h + b_k) - v(h)`` of each reported value
``v``, and the combined variance is the statistical one plus ``sum_k c_k^2`` (ADR 0028).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from rig.calibration.params import Array
from rig.calibration.residuals import Samples


@dataclass(frozen=True)
class FieldTerm:
    """One cage term at +1 sigma: the reference field's error as ``h -> h + matrix h + offset_ut``
    (``matrix`` 3x3, dimensionless; ``offset_ut`` (3,), uT); ``group`` names the source (a
    certificate, the field map, the lab field) and ``name`` the term within it."""

    name: str
    group: str
    matrix: Array = field(default_factory=lambda: np.zeros((3, 3)))
    offset_ut: Array = field(default_factory=lambda: np.zeros(3))

    def applied(self, field_ut: Array) -> Array:
        """``field_ut`` (N, 3) moved by this term."""
        h = np.asarray(field_ut, float)
        return np.asarray(h + h @ np.asarray(self.matrix).T + np.asarray(self.offset_ut))


def with_field(samples: Samples, field_ut: Array) -> Samples:
    """``samples`` with the reference field replaced (the magnitude follows it)."""
    return replace(samples, field_ut=field_ut, field_magnitude_ut=np.linalg.norm(field_ut, axis=1))


def corrected(samples: Samples, correction: FieldTerm | None) -> Samples:
    """``samples`` with a known correction of the field applied (the field at the DUT from the
    field at the reference, a map's estimate); unchanged for None."""
    if correction is None or samples.field_ut is None:
        return samples
    return with_field(samples, correction.applied(samples.field_ut))


@dataclass(frozen=True)
class TermContribution:
    """What one term moves the reported values by (their units)."""

    name: str
    group: str
    contribution: Array


@dataclass(frozen=True)
class UncertaintyBudget:
    """The statistical 1-sigma of the reported values and each cage term's contribution."""

    statistical: Array
    terms: tuple[TermContribution, ...]
    left_out: tuple[str, ...] = ()
    """Terms the budget could not state (what is missing to state them)."""

    @property
    def combined_sigma(self) -> Array:
        """1-sigma of each value with every term: statistical and terms in quadrature."""
        total = np.square(np.asarray(self.statistical, float))
        for t in self.terms:
            total = total + np.square(t.contribution)
        return np.asarray(np.sqrt(total))

    def groups(self) -> dict[str, Array]:
        """Each group's contribution per value (root sum of squares of its terms)."""
        out: dict[str, Array] = {}
        for t in self.terms:
            out[t.group] = np.hypot(out.get(t.group, 0.0), t.contribution)
        return out


def propagate(
    samples: Samples,
    refit: Callable[[Samples], Array],
    values: Array,
    statistical: Array,
    terms: Sequence[FieldTerm],
    left_out: Sequence[str] = (),
) -> UncertaintyBudget:
    """The budget of the reported ``values`` (1-sigma ``statistical``) fitted to ``samples``:
    ``refit`` (the same estimator and options, returning the values) run once per term on the
    field moved by it.

    Needs the field vector (a scalar fit is refitted on the moved field's magnitude)."""
    if samples.field_ut is None:
        raise ValueError("an uncertainty budget needs the reference field vector")
    out = []
    for term in terms:
        moved = refit(with_field(samples, term.applied(samples.field_ut)))
        out.append(TermContribution(term.name, term.group, np.asarray(moved - values, float)))
    return UncertaintyBudget(np.asarray(statistical, float), tuple(out), tuple(left_out))


@dataclass(frozen=True)
class CageTerms:
    """What a calibration is given of the cage: a correction of the reference field to the DUT's
    place (or None), the terms at +1 sigma, and the terms it could not state (why)."""

    correction: FieldTerm | None = None
    terms: tuple[FieldTerm, ...] = ()
    left_out: tuple[str, ...] = ()
