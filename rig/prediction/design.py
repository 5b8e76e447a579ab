"""The shortest calibration procedure that meets given sigma targets (``rig design``, ADR 0032).

Two parts, each an established method:

* **Where to put the fields: a D-optimal design by Fedorov's exchange algorithm** (Fedorov 1972;
  Atkinson, Donev and Tobias 2007, ch. 12). The vector model's regressors per DUT axis are
  ``(h_x, h_y, h_z, 1)`` (the scale and misalignment row and the offset); the candidates are
  field set-points in evenly spread directions at the lowest and the highest magnitude allowed.
  Starting from a random design of ``n`` candidates, every exchange of a design point for a
  candidate that raises ``det(X^T X)`` the most is made until none does. The loads are not
  designed point by point: each channel steps through its levels on a profile of its own (dwells
  of 3, 4, 5 ... set-points, so the level combinations meet fields all over the sphere), which
  keeps their coefficients apart from the field's.
* **How many points and how long each: the prediction** (:mod:`rig.prediction.predict`, ADR 0031)
  of each candidate procedure, the DUT's noise floor and the cage's terms included, and its time
  on the rig (ramps and polarity flips: :mod:`rig.prediction.duration`). The smallest design of
  each dwell that meets every target is found by bisection on ``n``; the shortest of them wins.

What cannot be met is said with the term that limits it (a scale target below the reference
certificate's 5e-5 cannot be met by any number of points).
"""

from __future__ import annotations

import fnmatch
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from rig.errors import UserInputError
from rig.prediction.designed_acceptance import Acceptance
from rig.steps.geometry import fibonacci_directions

Array = npt.NDArray[np.float64]
CANDIDATE_DIRECTIONS = 120
DWELLS_S = (0.6, 0.8, 1.2)
"""The dwells tried per set-point (s): shorter ones lose a larger share to settling."""
MARGIN = 0.25
"""Each predicted sigma is sized this much below its target by default: a run's noise varies about
the floor (the z residuals of two runs on the simulated cage: 20.5 and 29.7 nT)."""
MIN_POINTS = 8
MAX_POINTS = 400
SEED = 11


@dataclass(frozen=True)
class Targets:
    """What ``rig design`` is asked for: the calibration ``model``, the load channels whose
    coefficients are fitted with their allowed ``levels`` (A), the field ``magnitude_ut`` range,
    and the combined 1-sigma each value must reach (result paths, ``*`` wildcards)."""

    model: str
    loads: dict[str, list[float]]
    magnitude_ut: tuple[float, float]
    sigma: dict[str, float]
    source: str = ""
    dut: str = "dut"
    """The DUT's device name in the rig configuration (``dut:`` in the targets file)."""
    reference: str = "reference"
    """The reference magnetometer's device name (``reference:``)."""
    acceptance: Acceptance | None = None
    """With it, a whole acceptance procedure is written (:mod:`rig.prediction.designed_acceptance`)."""

    @classmethod
    def load(cls, path: Path) -> Targets:
        """Read a targets file; UserInputError naming what is wrong."""
        import yaml

        try:
            raw = yaml.safe_load(path.read_text(encoding="utf-8"))
        except (OSError, yaml.YAMLError) as exc:
            raise UserInputError(f"{path}: cannot read the targets ({exc})") from None
        if (
            not isinstance(raw, dict)
            or not isinstance(raw.get("targets"), dict)
            or not raw["targets"]
        ):
            raise UserInputError(f"{path}: needs 'targets:', a mapping of result values to their"
                                 " largest 1-sigma, e.g. springmann.a: 1.0e-4")  # fmt: skip
        model = str(raw.get("model", "vector"))
        if model not in ("vector", "scalar"):
            raise UserInputError(f"{path}: model must be vector or scalar, got {model!r}")
        loads = {
            str(k): [float(v) for v in vals] for k, vals in dict(raw.get("loads") or {}).items()
        }
        if any(len(v) < 2 for v in loads.values()):
            raise UserInputError(f"{path}: every load needs at least two levels (its coefficient"
                                 " is found from how the reading changes with it)")  # fmt: skip
        lo, hi = (float(v) for v in raw.get("magnitude_ut", [15.0, 45.0]))
        if not 0.0 < lo <= hi:
            raise UserInputError(f"{path}: magnitude_ut must be [low, high] with 0 < low <= high")
        sigma = {str(k): float(v) for k, v in raw["targets"].items()}
        if any(not v > 0 for v in sigma.values()):
            raise UserInputError(f"{path}: every target must be a positive 1-sigma")
        roles = {role: str(raw.get(role) or role) for role in ("dut", "reference")}
        acceptance = Acceptance.from_raw(raw.get("acceptance"), str(path))
        return cls(model, loads, (lo, hi), sigma, str(path), roles["dut"], roles["reference"],
                   acceptance)  # fmt: skip

    def limit(self, path: str) -> float | None:
        """The target of a result path (the first pattern that matches), None if it has none."""
        for pattern, value in self.sigma.items():
            if fnmatch.fnmatchcase(path, pattern):
                return value
        return None


def candidates(magnitude_ut: tuple[float, float], directions: int = CANDIDATE_DIRECTIONS) -> Array:
    """The candidate fields (uT): evenly spread directions at the lowest and highest magnitude."""
    units = fibonacci_directions(directions)
    mags = sorted(set(magnitude_ut))
    return np.vstack([m * units for m in mags])


def d_optimal(cands: Array, n: int, seed: int = SEED, max_passes: int = 50) -> Array:
    """Indices of ``n`` candidates maximizing ``det(X^T X)``, ``X`` rows ``(h, 1)`` (scaled):
    Fedorov's exchange from a random start (repeated points allowed, as in an exact design)."""
    x = np.column_stack([cands / np.max(np.linalg.norm(cands, axis=1)), np.ones(len(cands))])
    rng = np.random.default_rng(seed)
    design = list(rng.choice(len(cands), size=n, replace=n > len(cands)))
    ridge = 1e-9 * np.eye(x.shape[1])
    for _ in range(max_passes):
        m_inv = np.linalg.inv(x[design].T @ x[design] + ridge)
        d = np.einsum("ij,jk,ik->i", x, m_inv, x)  # the variance function at every candidate
        best, swap = 1e-9, None
        for pos, i in enumerate(design):
            d_ij = x[i] @ m_inv @ x.T
            gain = d - d[i] - d * d[i] + d_ij**2  # Fedorov's delta for exchanging i for each j
            j = int(np.argmax(gain))
            if gain[j] > best:
                best, swap = float(gain[j]), (pos, j)
        if swap is None:
            break
        design[swap[0]] = swap[1]
    return np.asarray(design, int)


@dataclass(frozen=True)
class Design:
    """A designed procedure: its YAML text, the number of set-points and dwell, the predicted
    time on the rig, and per target its predicted sigma; ``unmet`` names what it cannot meet."""

    text: str
    points: int
    dwell_s: float
    seconds: float
    achieved: dict[str, tuple[float, float]] = field(default_factory=dict)
    unmet: dict[str, str] = field(default_factory=dict)

    @property
    def meets(self) -> bool:
        """Every target met."""
        return not self.unmet


def procedure_text(targets: Targets, fields_ut: Array, dwell_s: float, characterize: bool,
                   header: list[str]) -> str:  # fmt: skip
    """The procedure as a person would write it: the cage characterized (when its model is only
    nominal), a null field for the noise floor, the designed set-points with the loads stepping,
    the calibration."""
    lines = [f"# {h}" if h else "#" for h in header]
    channels = list(targets.loads)
    lines += ["procedure: Designed calibration",
              "description: >",
              f"  Written by rig design for {Path(targets.source).name or 'the targets'}: the fewest"
              " set-points that meet every target, each field chosen by a D-optimal exchange.",
              f"magnetometers: {{dut: {targets.dut}, reference: {targets.reference}}}"]  # fmt: skip
    if channels:
        lines.append(f"loads: [{', '.join(channels)}]")
    lines.append("steps:")
    if characterize:
        # 5 samples a direction: the model places the fields and sizes the trim; the calibration
        # uses the field the reference measures (10 cost 3.5 s more of a one-minute acceptance)
        lines += ["  - characterize_cage: {amplitude_a: 1.0, samples: 5, repeats: 1}",
                  "    name: cage model"]  # fmt: skip
    lines += ["  - null_field: {hold_s: 4, trim: yes}", "    name: noise floor",
              "  - field_points:", f"      dwell_s: {dwell_s:g}", "      fields_ut:"]  # fmt: skip
    lines += [f"        - [{f[0]:.2f}, {f[1]:.2f}, {f[2]:.2f}]" for f in fields_ut]
    lines.append("    name: designed fields")
    if channels:
        lines.append("    loads:")
        for j, (ch, levels) in enumerate(targets.loads.items()):
            lines.append(f"      {ch}: {{steps: {{levels_a: [{', '.join(f'{v:g}' for v in levels)}],"
                         f" dwell_s: {(3 + j) * dwell_s:g}}}}}")  # fmt: skip
    lines += [f"  - calibrate: {{model: {targets.model}, telemetry: [{', '.join(channels)}],"
              " steps: [designed fields]}", "    name: calibration", "  - report: {}"]  # fmt: skip
    return "\n".join(lines) + "\n"


def judge(targets: Targets, rows: dict[str, Any], margin: float = 0.0
          ) -> tuple[dict[str, tuple[float, float]], dict[str, str]]:  # fmt: skip
    """Per target-bearing value (predicted combined, target) and the unmet ones with why: met
    when the prediction times ``1 + margin`` is within the target."""
    achieved, unmet = {}, {}
    for path, row in rows.items():
        limit = targets.limit(path)
        if limit is None:
            continue
        achieved[path] = (row.combined, limit)
        if row.combined * (1.0 + margin) > limit:
            unmet[path] = (f"predicted {row.combined:.3g} (x {1 + margin:g} margin) > {limit:g},"
                           f" limited by {row.limited_by}")  # fmt: skip
    missing = [p for p in targets.sigma if not any(fnmatch.fnmatchcase(r, p) for r in rows)]
    for pattern in missing:
        unmet[pattern] = "no value of the calibration matches it"
    return achieved, unmet


def points_needed(sizes: list[int], meets: Any) -> int | None:
    """The smallest of the increasing ``sizes`` for which ``meets(n)`` holds (bisection; it is
    taken to hold for every larger size once it holds), None if not even the largest."""
    if not sizes or not meets(sizes[-1]):
        return None
    lo, hi = 0, len(sizes) - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if meets(sizes[mid]):
            hi = mid
        else:
            lo = mid + 1
    return sizes[lo]


def tour(fields_ut: Array) -> Array:
    """The fields in a nearest-neighbour order from the first (shorter ramps between them)."""
    left = list(range(1, len(fields_ut)))
    order = [0]
    while left:
        here = fields_ut[order[-1]]
        nearest = min(left, key=lambda i: float(np.sum((fields_ut[i] - here) ** 2)))
        order.append(nearest)
        left.remove(nearest)
    return np.asarray(fields_ut[order])


def sizes_up_to(max_points: int) -> list[int]:
    """Design sizes tried: every size to 24, then steps of about 10 %."""
    out = list(range(MIN_POINTS, min(24, max_points) + 1))
    n = 24
    while n < max_points:
        n = min(max_points, math.ceil(n * 1.1))
        out.append(n)
    return out


def design_procedure(targets: Targets, cfg: Any, timing: Any, noise: Any, cage: Any,
                     max_s: float | None = None, margin: float = MARGIN,
                     also_fit: tuple[str, ...] = ()) -> Design:  # fmt: skip
    """The shortest designed procedure meeting ``targets`` (each predicted sigma times ``1 +
    margin`` within its target: a run's noise varies about the floor) on the rig ``cfg`` with
    the noise floor ``noise`` and the cage's terms ``cage``, within ``max_s`` of time on the rig
    when given; when none meets them, the best found with what it cannot meet. ``also_fit``: the
    other calibration models the same set-points must give (an acceptance's scalar fit: 12
    set-points met the vector targets, and the scalar fit's ellipsoid was not valid on them)."""
    import tempfile

    from rig.output_limits import cage_model
    from rig.prediction.duration import predicted_duration
    from rig.prediction.planned import dut_rate_hz, planned_data
    from rig.prediction.predict import predict_step
    from rig.prediction.procedure import cage_limits
    from rig.procedure.language import parse_procedure

    model = cage_model(cfg) if cfg is not None else None
    characterize = model is None or bool(model.meta.get("nominal"))
    limits = cage_limits(cfg)
    cands = candidates(targets.magnitude_ut)
    rate = dut_rate_hz(cfg, targets.dut)
    tried: dict[tuple[int, float], Design] = {}

    def build(n: int, dwell: float) -> Design:
        if (n, dwell) in tried:
            return tried[(n, dwell)]
        fields = tour(cands[d_optimal(cands, n)])
        text = procedure_text(targets, fields, dwell, characterize, [])
        with tempfile.TemporaryDirectory(prefix="rig-design-") as tmp:
            path = Path(tmp) / "designed.yaml"
            path.write_text(text)
            proc = parse_procedure(path)
            fit = next(s for s in proc.steps if s.kind == "calibrate")
            planned = planned_data(proc, fit, timing, rate)
            pred = predict_step(fit.name, fit.params, planned, noise, cage)
            seconds = predicted_duration(proc, model, limits, timing).total_s
            others = {m: predict_step(m, fit.params | {"model": m}, planned, noise, cage).problem
                      for m in also_fit}  # fmt: skip
        achieved, unmet = judge(targets, pred.by_path(), margin)
        unmet |= {f"the {m} calibration": why for m, why in others.items() if why is not None}
        if pred.problem is not None:
            unmet = {"the calibration": pred.problem}
        if max_s is not None and seconds > max_s:
            unmet = unmet | {"time": f"{seconds:.0f} s on the rig > --max-s {max_s:g}"}
        tried[(n, dwell)] = Design(text, n, dwell, seconds, achieved, unmet)
        return tried[(n, dwell)]

    best: Design | None = None
    for dwell in DWELLS_S:
        n = points_needed(sizes_up_to(MAX_POINTS), lambda k, d=dwell: build(k, d).meets)
        if n is not None and (best is None or build(n, dwell).seconds < best.seconds):
            best = build(n, dwell)
    if best is None:  # nothing meets them: the design with the fewest unmet, then the shortest
        best = min(tried.values(), key=lambda d: (len(d.unmet), d.seconds))
    return best
