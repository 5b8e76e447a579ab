"""From recorded data to results: settled windows, noise floor, calibration, acceptance checks."""

from __future__ import annotations

import itertools
from collections.abc import Callable, Collection
from dataclasses import replace
from typing import Any, NamedTuple

import numpy as np
import numpy.typing as npt

from rig.calibration import Samples, calibrate
from rig.calibration.budget import CageTerms, UncertaintyBudget, corrected, propagate
from rig.calibration.estimators import DEFAULT_METHOD, estimator
from rig.calibration.record import CalibrationRecord, SampleSelection
from rig.calibration.result import CalibrationResult
from rig.errors import CalibrationError, UserInputError
from rig.store.run_states import Verdict
from rig.store.run_store import RunReader
from rig.timing import MisdatedHold, misdated_note, misdated_samples, timing_fault

Array = npt.NDArray[np.float64]

UNRESOLVED_SIGMA = 8.0
"""A reference sample whose second difference is this many robust standard deviations beyond the
others' marks a field change faster than the reference rate resolves."""


class PairedSamples(NamedTuple):
    """DUT samples paired with the reference field and load currents at their times."""

    samples: Samples
    t_s: Array
    """Monotonic time of each sample (s)."""
    unresolved: int
    """DUT samples left out because the field moved faster than the reference could follow (a
    jump between its samples, or a tracked timeline that ran late: :func:`late_intervals`)."""
    misdated: tuple[MisdatedHold, ...] = ()
    """Holds where the DUT moved while the reference and every command held still: those samples
    are left out (:func:`rig.timing.misdated_samples`)."""
    late: int = 0
    """Of ``unresolved``, those taken while a tracked timeline ran irregularly
    (:func:`late_intervals`)."""


TRACK_RAMP_S = 0.01
"""A tracked set-point logged without ``ramped`` (runs before it was recorded) that took longer
than this (s) from issue to done counts as having ramped."""


LATE_LIMIT_PERIODS = 0.6
"""A tracked command sent sooner after the previous one on the same output than planned, by more
than this many reference sample periods (30 ms at 20 Hz), was part of a burst."""
LATE_MARGIN_PERIODS = 3.0
"""DUT samples up to this many reference periods after an irregular tracked command was done are
left out with it: the field and currents catch up over the next few reference samples."""


def change_times(reader: RunReader) -> Array:
    """(start, end) of every field and load change: a field command is logged when its ramp (or
    trim) has finished and carries the time it was issued; a load change is instantaneous. A
    tracked set-point (orbit replay) is no change unless it ramped (a polarity flip), nor is a
    tracked load step: the reference and the telemetry follow them, and settling after each
    set-point would leave nothing."""
    rows = [(float(p.get("t_issued", t)), t) for t, _, kind, p in reader.commands()
            if _is_change(kind, t, p)]  # fmt: skip
    return np.array(rows, float).reshape(-1, 2)


def _is_change(kind: str, t: float, payload: dict[str, Any]) -> bool:
    """A field or load command to settle after: not a tracked one, unless a tracked field
    set-point ramped."""
    if kind not in ("field", "load"):
        return False
    if not payload.get("track"):
        return True
    issued = float(payload.get("t_issued", t))
    return kind == "field" and bool(payload.get("ramped", t - issued > TRACK_RAMP_S))


def late_intervals(reader: RunReader, limit_s: float) -> Array:
    """(start, end) of every burst on a tracked timeline (an orbit replay's set-points, each load
    channel's currents): a command sent sooner after its predecessor on the same output than
    their due times are apart, by more than ``limit_s`` (s), from the predecessor's issue to this
    one's done. The computer held the timeline back and then caught up: the output moved faster
    than planned, faster than the reference's samples resolve (issue 30: delays 4 sigma off, a
    scalar residual over its limit). A timeline that is late by a steady or growing amount (a
    slow link) only holds each set-point longer, which the reference follows. Runs recorded
    before commands carried their due time have none. Since a late tracked timeline slips
    instead of catching up (rig.engine.schedule.TrackPace), runs recorded since find none unless
    the computer stalled inside a set-point's group."""
    series: dict[tuple[str, str], list[tuple[float, float, float]]] = {}
    for t, _, kind, p in reader.commands():
        if kind in ("field", "load") and p.get("track") and "t_due" in p:
            # the plan's spacing where recorded (a slipped timeline's due times embed its slips)
            planned = float(p.get("t_plan", p["t_due"]))
            series.setdefault((kind, str(p.get("channel", ""))), []).append(
                (planned, float(p.get("t_issued", t)), t)
            )
    rows = []
    for cmds in series.values():
        for (due0, issued0, _), (due1, issued1, done1) in itertools.pairwise(cmds):
            if (due1 - due0) - (issued1 - issued0) > limit_s:
                rows.append((issued0, done1))
    return np.array(rows, float).reshape(-1, 2)


def settled(
    times: Array, changes: Array, settle_s: float, t_unc_s: Array | None = None
) -> npt.NDArray[np.bool_]:
    """True for samples outside every change interval extended by ``settle_s`` after its end;
    with ``t_unc_s`` (s per sample, NaN unknown), a sample is outside only when its whole
    interval t +- t_unc is (ADR 0020: a stall widens what is left out, never shifts it)."""
    unc = np.zeros(times.shape) if t_unc_s is None else np.nan_to_num(t_unc_s, nan=0.0)
    ok = np.ones(times.shape, bool)
    for start, end in changes.reshape(-1, 2):
        ok &= ~((times + unc >= start) & (times - unc < end + settle_s))
    return ok


def step_windows(
    reader: RunReader, names: list[str] | None, field_kinds: Collection[str]
) -> list[tuple[float, float]]:
    """(start, end) of the named steps, or of every step of ``field_kinds`` when ``names`` is
    empty (``rig.steps.field_kinds()``: the kinds that set fields)."""
    out = []
    for _, name, kind, t0, t1 in reader.steps():
        if t1 is None:
            continue
        if (names and name in names) or (not names and kind in field_kinds):
            out.append((t0, t1))
    return out


def _in_windows(t: Array, windows: list[tuple[float, float]]) -> npt.NDArray[np.bool_]:
    mask = np.zeros(t.shape, bool)
    for a, b in windows:
        mask |= (t >= a) & (t <= b)
    return mask


def to_cage_frame(xyz: Array, correction: dict[str, Any] | None) -> Array:
    """Reference readings through its certificate: ``h = M (m - o)``."""
    if not correction:
        return xyz
    m = np.array(correction["matrix"], float)
    o = np.array(correction["offset_ut"], float)
    return np.asarray((xyz - o) @ m.T)


def apply_correction(correction: dict[str, Any], measured_ut: Array, telemetry: Array,
                     channels: list[str]) -> Array:  # fmt: skip
    """A result file's correction ``h = matrix (m - offset - sum_j k_j u_j)`` of readings
    ``measured_ut`` (N, 3) uT with telemetry (N, J) in the order of ``channels``."""
    k = np.array([correction["k_ut_per_unit"][c] for c in channels], float).reshape(-1, 3)
    bias = np.asarray(telemetry, float) @ k if k.size else 0.0
    return to_cage_frame(np.asarray(measured_ut, float) - bias, correction)


def apply_correction_unloaded(correction: dict[str, Any], measured_ut: Array) -> Array:
    """:func:`apply_correction` with every load channel of the correction at 0 A."""
    channels = list(correction.get("k_ut_per_unit", {}))
    return apply_correction(correction, measured_ut, np.zeros((len(measured_ut), len(channels))),
                            channels)  # fmt: skip


def hold_values(reader: RunReader, channel: str, t: Array) -> Array:
    """A channel's measured current (A) at times ``t`` (the last reading before each time)."""
    rows = [
        (tt, m if m is not None else c)
        for tt, c, m in reader.channel(channel)
        if (m if m is not None else c) is not None
    ]
    if not rows:
        return np.zeros_like(t)
    ts = np.array([r[0] for r in rows])
    vs = np.array([r[1] for r in rows], float)
    idx = np.clip(np.searchsorted(ts, t, side="right") - 1, 0, None)
    return np.asarray(vs[idx])


def telemetry_series(reader: RunReader, channel: str, width_s: float) -> Callable[[Array], Array]:
    """A channel's set-points as a function of time (A), for delay estimation
    (:func:`staircase_series`). A load command counts from the middle of its write; read-backs
    serve a channel that was never commanded."""
    cmds = load_commands(reader, channel)
    if cmds.shape[0]:
        return staircase_series(0.5 * (cmds[:, 0] + cmds[:, 1]), cmds[:, 2], width_s)
    rows = np.array(reader.channel_column(channel, "measured"), float).reshape(-1, 2)
    if not rows.size:
        return lambda times: np.zeros_like(times)
    return staircase_series(rows[:, 0], rows[:, 1], width_s)


def load_commands(reader: RunReader, channel: str) -> Array:
    """Rows (issued s, done s, current A) of every command to load ``channel``."""
    rows = [(float(p.get("t_issued", t)), t, float(p["current_a"]))
            for t, _, kind, p in reader.commands()
            if kind == "load" and p.get("channel") == channel]  # fmt: skip
    return np.array(rows, float).reshape(-1, 3)


def phase_locked_interval_s(commands: Array, t_s: Array) -> float | None:
    """The interval (s) of load ``commands`` (:func:`load_commands`) when the DUT samples ``t_s``
    (s) fall at nearly the same phase of it (resultant length of the phases above 0.5): every
    sample then sees the same part of each step, and a delay is known only to within that
    interval. None otherwise. Commands sent only when the value changes (a panel current) are
    multiples of their schedule's step: the interval is that step (the tenth percentile of the
    gaps), not the typical gap."""
    starts = commands[:, 1]
    if starts.size < 10 or t_s.size < 10:
        return None
    interval = float(np.percentile(np.diff(starts), 10))
    if not interval > 0:
        return None
    locked = abs(np.mean(np.exp(2j * np.pi * t_s / interval))) > 0.5
    return interval if locked else None


def write_window_s(commands: Array, t_s: Array, ramp_s: float) -> float:
    """The width (s) within which a load channel's ``commands`` (:func:`load_commands`) took
    effect, as it bears on the channel's delay: each command's write (issued .. answered)
    weighted by its share of the delay's information, its current step squared times the DUT
    samples ``t_s`` (s) within ``ramp_s`` of it (the series' ramp, :func:`staircase_series`).
    Where in its write a command acted is one unknown for them all, not one each (on a busy
    computer the answer comes late while the device acted early), so it is their weighted mean,
    not a width that averages down; a median let a few wide writes on large steps (an eclipse
    entry) bias an orbit replay's delay by 2 of its sigma (issue 30)."""
    if commands.shape[0] == 0:
        return 0.0
    widths = commands[:, 1] - commands[:, 0]
    mid = 0.5 * (commands[:, 0] + commands[:, 1])
    steps = np.abs(np.diff(np.r_[0.0, commands[:, 2]]))
    near = np.searchsorted(t_s, mid + 0.5 * ramp_s) - np.searchsorted(t_s, mid - 0.5 * ramp_s)
    weight = steps**2 * near
    if not weight.sum() > 0:
        return float(np.median(widths))
    return float(weight @ widths / weight.sum())


def staircase_series(starts_s: Array, values: Array, width_s: float) -> Callable[[Array], Array]:
    """Values that each hold from their start (s, increasing) to the next one's, as a function of
    time: each step a linear ramp ``width_s`` (s) wide centred on it (steps closer than that: the
    line through the middle of each hold). The profile of a delay is then smooth and unbiased,
    where sampling the staircase at the DUT's times moves every step to the next sample (half a
    sample period late on average)."""
    ends = np.r_[starts_s[1:], np.inf]
    pts_t: list[float] = []
    pts_v: list[float] = []
    for start, end, value in zip(starts_s, ends, values, strict=True):
        if end - start <= width_s:
            pts_t.append(0.5 * (start + end))
            pts_v.append(float(value))
        else:
            pts_t += [start + 0.5 * width_s, end - 0.5 * width_s]
            pts_v += [float(value), float(value)]
    knots_t = np.array(pts_t[:-1] if np.isinf(pts_t[-1]) else pts_t)
    knots_v = np.array(pts_v[: knots_t.size])

    def at(times: Array) -> Array:
        return np.asarray(np.interp(times, knots_t, knots_v))

    return at


def spread_nt(xyz_ut: Array) -> float:
    """RMS over the three axes of the sample standard deviation: uT rows in, nT out."""
    return float(1000.0 * np.sqrt(np.mean(np.var(xyz_ut, axis=0, ddof=1))))


def settled_samples(
    reader: RunReader,
    device: str,
    window: tuple[float, float],
    settle_s: float,
    changes: Array | None = None,
) -> Array:
    """Rows (t s, x, y, z uT) of ``device`` inside ``window`` and outside every field or load
    change extended by ``settle_s`` (s); ``changes`` (from :func:`change_times`) when the caller
    already has them."""
    changes = change_times(reader) if changes is None else changes
    dated = np.array(reader.dated_samples(device), float).reshape(-1, 5)
    rows = dated[:, :4]
    keep = _in_windows(rows[:, 0], [window]) & settled(rows[:, 0], changes, settle_s, dated[:, 4])
    return rows[keep]


def paired_noise(
    reader: RunReader, window: tuple[float, float], device: str, reference: str, settle_s: float
) -> float | None:
    """RMS over axes of the standard deviation (nT) of ``device`` minus the newest ``reference``
    sample before it, in a settled window: the noise of the pairs a sequential calibration sees.
    Field noise both magnetometers see at the same moment cancels here; the root sum square of
    the two noise floors counts it twice. None with fewer than 5 pairs."""
    changes = change_times(reader)
    dut = settled_samples(reader, device, window, settle_s, changes)
    ref = settled_samples(reader, reference, window, settle_s, changes)
    if len(ref) == 0:
        return None
    idx = np.searchsorted(ref[:, 0], dut[:, 0], side="right") - 1
    ok = idx >= 0
    if ok.sum() < 5:
        return None
    return spread_nt(dut[ok, 1:] - ref[idx[ok], 1:])


def noise_floor(
    reader: RunReader, window: tuple[float, float], devices: list[str], settle_s: float
) -> dict[str, float]:
    """Per device: RMS over axes of the sample standard deviation in a settled window (nT)."""
    changes = change_times(reader)
    out = {}
    for dev in devices:
        rows = settled_samples(reader, dev, window, settle_s, changes)
        if len(rows) >= 5:
            out[dev] = spread_nt(rows[:, 1:])
    return out


def calibration_data(
    reader: RunReader,
    dut: str,
    reference: str,
    telemetry: list[str],
    steps: list[str],
    settle_s: float,
    correction: dict[str, Any] | None,
    field_kinds: Collection[str] = (),
    leave_out_late: bool = True,
) -> PairedSamples:
    """DUT readings with the reference field (cage frame) and load currents at the same times
    (with ``settle_s`` > 0 numbered by hold: a field or load change starts the next).

    A DUT sample is left out (and counted) when the reference samples around it show the field
    jumping between them (:func:`unresolved_field`): the reference cannot say which field the DUT
    saw. Polarity flips, ramps and commands a supply took late (a busy computer) make such jumps.
    With holds, DUT samples that moved at the edge of a hold while the reference and every
    command held still contradict their dates and are left out too (rig.timing)."""
    dated = np.array(reader.dated_samples(dut), float).reshape(-1, 5)
    rows, t_unc = dated[:, :4], dated[:, 4]
    ref = np.array(reader.samples(reference), float).reshape(-1, 4)
    if rows.shape[0] == 0 or ref.shape[0] < 2:
        raise CalibrationError(
            f"no samples of '{dut}' or '{reference}' in this run: check the magnetometers"
        )
    t = rows[:, 0]
    # The reference is interpolated at each DUT time: a sample less than a reference period before
    # a step change would mix in a reference reading taken during the ramp (seen as 0.5-0.8 uT
    # errors). settle_s = 0 declares a tracked field (orbit replay), where interpolating is right.
    changes = change_times(reader)
    issued_s = changes[:, 0].copy()
    if settle_s > 0:
        changes[:, 0] -= 1.5 * float(np.median(np.diff(ref[:, 0])))
    keep = _in_windows(t, step_windows(reader, steps, field_kinds))
    keep &= settled(t, changes, settle_s, t_unc if settle_s > 0 else None)
    keep &= (t >= ref[0, 0]) & (t <= ref[-1, 0])
    late = _in_bursts(reader, t, t_unc, ref[:, 0]) & keep if leave_out_late else np.zeros_like(keep)
    keep &= ~late
    if keep.sum() == 0:
        raise CalibrationError(
            "no settled DUT samples in the selected steps: hold each field longer than settle_s"
        )
    jumps = unresolved_field(ref, t[keep])
    if jumps.all():
        raise CalibrationError(
            "the field moved faster than the reference could follow at every DUT sample"
        )
    keep[keep] = ~jumps
    misdated: list[MisdatedHold] = []
    if settle_s > 0:
        wrong, misdated = misdated_samples(t, rows[:, 1:], keep, ref[:, 0], ref[:, 1:], issued_s)
        keep &= ~wrong
    t = t[keep]
    field = interpolated_field(ref, t, correction)
    u = np.column_stack([hold_values(reader, ch, t) for ch in telemetry]) if telemetry else None
    samples = Samples.build(rows[keep, 1:], field_ut=field, telemetry=u, channels=tuple(telemetry),
                            holds=hold_numbers(issued_s, t) if settle_s > 0 else None)  # fmt: skip
    unresolved = int(jumps.sum() + late.sum())
    return PairedSamples(samples, t, unresolved, tuple(misdated), int(late.sum()))


def hold_numbers(changes_s: Array, t_s: Array) -> Array:
    """Per sample time ``t_s`` (s) the number of changes (issued at ``changes_s``, s) before it:
    the hold it was taken in."""
    return np.asarray(np.searchsorted(np.sort(changes_s), t_s, side="right"))


def interpolated_field(ref: Array, t_s: Array, correction: dict[str, Any] | None) -> Array:
    """Reference readings (rows t s, x, y, z uT) interpolated at ``t_s`` (s) and taken through
    the reference's certificate: the field in the cage frame (N, 3) uT."""
    field = np.column_stack([np.interp(t_s, ref[:, 0], ref[:, 1 + i]) for i in range(3)])
    return to_cage_frame(field, correction)


def offsets_less_reference(rows: Array, ref: Array | None, dut_correction: dict[str, Any] | None,
                           ref_correction: dict[str, Any] | None) -> tuple[Array, Array]:  # fmt: skip
    """A DUT's readings at rest (rows t s, x, y, z uT) as its offset: corrected by
    ``dut_correction`` (a calibration's, without load currents) when given, less the reference
    (rows likewise; through ``ref_correction``, its certificate) interpolated at each DUT time,
    where the reference covers it. Times (s) and offsets (nT, (N, 3))."""
    t, m = rows[:, 0], rows[:, 1:]
    if dut_correction is not None:
        m = apply_correction_unloaded(dut_correction, m)
    if ref is not None and len(ref) >= 2:
        keep = (t >= ref[0, 0]) & (t <= ref[-1, 0])
        t, m = t[keep], m[keep]
        m = m - interpolated_field(ref, t, ref_correction)
    return t, 1000.0 * m


def reference_field_series(reader: RunReader) -> Callable[[Array], Array]:
    """The run's reference field (cage frame, uT, (N, 3)) at any times (s), interpolated as
    :func:`calibration_data` does at the DUT's dates."""
    meta = reader.meta()
    name = meta.get("magnetometers", {}).get("reference", "reference")
    ref = np.array(reader.samples(name), float).reshape(-1, 4)
    correction = meta.get("reference_correction")
    return lambda t_s: interpolated_field(ref, np.asarray(t_s, float), correction)


def _in_bursts(reader: RunReader, t: Array, t_unc: Array, ref_t: Array) -> npt.NDArray[np.bool_]:
    """True for the DUT samples (dates ``t`` +- ``t_unc``, s) taken in or just after a burst of
    a tracked timeline (:func:`late_intervals`), judged in the reference's periods (``ref_t``)."""
    ref_period_s = float(np.median(np.diff(ref_t)))
    bursts = late_intervals(reader, LATE_LIMIT_PERIODS * ref_period_s)
    return ~settled(t, bursts, LATE_MARGIN_PERIODS * ref_period_s, t_unc)


def unresolved_field(ref: Array, t_s: Array) -> npt.NDArray[np.bool_]:
    """True for each time in ``t_s`` (s) whose bracketing reference samples (rows t s, x, y, z uT)
    include one whose second difference is an outlier (:data:`UNRESOLVED_SIGMA` robust standard
    deviations of those in the span of ``t_s``, any axis): there the field changed within a
    reference period and no interpolation recovers it. Steady tracking and noise pass."""
    out = np.zeros(t_s.shape, bool)
    if ref.shape[0] < 5 or t_s.size == 0:
        return out
    d2 = np.abs(ref[2:, 1:] - 2.0 * ref[1:-1, 1:] + ref[:-2, 1:])
    mid = ref[1:-1, 0]
    span = (mid >= t_s.min()) & (mid <= t_s.max())
    if span.sum() < 5:
        return out
    typical = d2[span]
    sigma = 1.4826 * np.median(np.abs(typical - np.median(typical, axis=0)), axis=0)
    jump = np.zeros(ref.shape[0], bool)
    jump[1:-1] = np.any(d2 > UNRESOLVED_SIGMA * np.maximum(sigma, 1e-9), axis=1)
    i = np.clip(np.searchsorted(ref[:, 0], t_s, side="right") - 1, 0, ref.shape[0] - 2)
    return jump[i] | jump[i + 1]


def stored_run_data(
    reader: RunReader,
    telemetry: list[str],
    settle_s: float = 0.25,
    *,
    field_kinds: Collection[str],
) -> PairedSamples:
    """:func:`calibration_data` of every field step (``field_kinds``: rig.steps.field_kinds())
    of a finished run, with the DUT, reference and reference certificate its metadata recorded
    (``rig calibrate RUN``: a new fit of the whole run)."""
    meta = reader.meta()
    mags = meta.get("magnetometers", {"dut": "dut", "reference": "reference"})
    return calibration_data(reader, mags.get("dut", "dut"), mags.get("reference", "reference"), telemetry,
                            [], settle_s, meta.get("reference_correction"), field_kinds)  # fmt: skip


def selected_data(
    reader: RunReader,
    record: CalibrationRecord,
    *,
    field_kinds: Collection[str],
    telemetry: list[str] | None = None,
) -> PairedSamples:
    """The samples a stored calibration was fitted on, selected again from its own stored
    selection (steps, settling, exclusions); ``telemetry``: other channels (``[]``: none) for a
    comparison on the same samples. A result recorded before results named their selection:
    every field step settled 0.25 s, as the report then did."""
    channels = list(record.channels) if telemetry is None else telemetry
    sel = record.selection
    if sel is None:
        return stored_run_data(reader, channels, field_kinds=field_kinds)
    return calibration_data(reader, sel.dut, sel.reference, channels, list(sel.steps), sel.settle_s,
                            reader.meta().get("reference_correction"), field_kinds)  # fmt: skip


def calibrate_run(reader: RunReader, params: dict[str, Any], magnetometers: dict[str, str],
                  correction: dict[str, Any] | None, field_kinds: Collection[str],
                  cage: CageTerms | None = None) -> dict[str, Any]:  # fmt: skip
    """The ``calibrate`` step: fit the DUT from the run so far (the named steps, or every step of
    ``field_kinds``); returns the result file content, with the selection it was fitted on and,
    given the ``cage``'s terms, the reference field corrected to the DUT's place and the
    uncertainty budget (``combined_sigma``, ``uncertainty_budget``; ADR 0028)."""
    dut = magnetometers.get(params["magnetometer"], params["magnetometer"])
    reference = magnetometers.get("reference", "reference")
    steps = [n for _, n, k, _, t1 in reader.steps() if t1 is not None
             and ((params["steps"] and n in params["steps"]) or (not params["steps"] and k in field_kinds))]  # fmt: skip
    samples, t_s, unresolved, misdated, late = calibration_data(
        reader, dut, reference, params["telemetry"], params["steps"], params["settle_s"],
        correction, field_kinds)  # fmt: skip
    late_fault = late_timeline_fault(late, samples.n + unresolved)
    if late_fault is not None:  # numbers from every sample, shown but not judged
        samples, t_s, unresolved, misdated, late = calibration_data(
            reader, dut, reference, params["telemetry"], params["steps"], params["settle_s"],
            correction, field_kinds, leave_out_late=False)  # fmt: skip
    method = params["method"] or DEFAULT_METHOD[params["model"]]
    if params["model"] == "scalar" and estimator(method).model == "vector":
        raise CalibrationError(f"a scalar calibration cannot use method '{method}'")
    temperature, no_temperature = None, 0
    if params.get("temperature"):
        samples, temperature, no_temperature = run_temperature(
            reader, params["temperature"], samples, t_s
        )
    samples = corrected(samples, cage.correction if cage is not None else None)

    def refit(s: Samples) -> CalibrationResult:
        return calibrate(s, method, noise_nt=params["noise_nt"] or None, temperature=temperature,
                         temperature_ref=params.get("temperature_ref_c"))  # fmt: skip

    fit = refit(samples)
    n_misdated = int(sum(m.samples for m in misdated))
    fault = timing_fault(misdated, samples.n + unresolved + n_misdated) if misdated else None
    fault = late_fault or fault
    selection = SampleSelection(tuple(steps), float(params["settle_s"]), tuple(params["telemetry"]),
                                dut, reference, unresolved, n_misdated,
                                float(max((abs(m.early_s) for m in misdated), default=0.0)),
                                fault)  # fmt: skip
    warnings = list(fit.warnings)
    if no_temperature:
        warnings.insert(0, f"{no_temperature} samples left out: no {params['temperature']}"
                        f" reading within {MAX_TEMPERATURE_GAP_S:g} s")  # fmt: skip
    if unresolved:
        warnings.insert(0, unresolved_note(unresolved, samples.n + unresolved))
    if misdated:
        warnings.insert(0, misdated_note(misdated, samples.n + unresolved + selection.misdated))
    if fault is not None:
        warnings.insert(0, fault)
    record = CalibrationRecord.from_dict(fit.to_dict())
    out = replace(record, selection=selection, warnings=tuple(warnings)).to_dict()
    if cage is not None:
        out |= budget_block(fit, propagate(samples, lambda s: refit(s).reported(), fit.reported(),
                                           fit.reported_sigma(), cage.terms, cage.left_out))  # fmt: skip
    return out


def budget_block(fit: CalibrationResult, budget: UncertaintyBudget) -> dict[str, Any]:
    """The result's ``combined_sigma`` (as ``sigma``) and ``uncertainty_budget``: each term's
    contribution, each group's, what was left out and how it was propagated."""
    return {
        "combined_sigma": fit.grouped(budget.combined_sigma),
        "uncertainty_budget": {
            "propagation": PROPAGATION,
            "statistical": fit.grouped(budget.statistical),
            "groups": {g: fit.grouped(c) for g, c in budget.groups().items()},
            "terms": [{"name": t.name, "group": t.group, "contribution": fit.grouped(t.contribution)}
                      for t in budget.terms],
            "left_out": list(budget.left_out),
        },
    }  # fmt: skip


PROPAGATION = ("GUM linear propagation: each cage term's sensitivity by refitting the data with the"
               " reference field moved by its 1-sigma; terms independent, combined in quadrature"
               " with the statistical covariance (ADR 0028)")  # fmt: skip


def late_timeline_fault(late: int, total: int) -> str | None:
    """Why a calibration on a tracked timeline cannot be judged, or None: more than
    :data:`MAX_LATE_FRACTION` of its ``total`` DUT samples were taken while the timeline ran
    irregularly (:func:`late_intervals`), so what is left is no longer the planned data."""
    if late <= MAX_LATE_FRACTION * max(total, 1):
        return None
    return (f"timing fault: {late} of {total} DUT samples were taken while this computer ran the"
            " tracked timeline irregularly (commands held back, then sent in bursts); the data"
            " cannot be trusted for a verdict: re-run the step on a less busy computer")  # fmt: skip


MAX_LATE_FRACTION = 0.5
"""A tracked timeline that ran irregularly for more than this fraction of the DUT samples makes
its calibration a timing fault (a re-run), not a fit on the remaining few."""
CLOCK_OFFSET_MIN_BOUND_S = 0.05
"""The offset between a DUT's and the reference's dates is searched within at least this (s)."""
MAX_TEMPERATURE_GAP_S = 3.0
"""A sample further than this from every reading of the thermometer (3 of its periods) has no
temperature to speak of: it is left out of a temperature fit, and the count said."""


def recorded_thermometer(reader: RunReader, name: str) -> None:
    """UserInputError unless the run recorded thermometer ``name`` (naming those it did)."""
    recorded = list(reader.meta().get("thermometers") or [])
    if name not in recorded:
        have = ", ".join(recorded) or "none (the rig configuration had no thermometer)"
        raise UserInputError(f"--temperature {name}: the run recorded no such thermometer; it"
                             f" recorded: {have}")  # fmt: skip


def run_temperature(
    reader: RunReader, name: str, samples: Samples, t_s: Array
) -> tuple[Samples, Array, int]:
    """The DUT temperature (C) a run's thermometer ``name`` recorded, interpolated linearly to
    the calibration samples' times ``t_s`` (s): (samples kept, temperature per kept sample,
    number left out for want of a reading within :data:`MAX_TEMPERATURE_GAP_S`)."""
    temperature, keep = thermometer_at(reader, name, t_s)
    return samples.take(keep), temperature[keep], int((~keep).sum())


def thermometer_at(reader: RunReader, name: str, t_s: Array) -> tuple[Array, Any]:
    """Thermometer ``name``'s temperature (C) interpolated at ``t_s`` (s) and which times have a
    reading within :data:`MAX_TEMPERATURE_GAP_S`; UserInputError when the run has none."""
    recorded_thermometer(reader, name)
    rows = np.array(reader.channel_column(name, "measured"), float).reshape(-1, 2)
    if rows.size == 0:
        raise UserInputError(f"--temperature {name}: the thermometer never answered in this run")
    t_th, value = rows[:, 0], rows[:, 1]
    right = np.clip(np.searchsorted(t_th, t_s), 0, len(t_th) - 1)
    left = np.clip(right - 1, 0, len(t_th) - 1)
    nearest = np.minimum(np.abs(t_th[right] - t_s), np.abs(t_s - t_th[left]))
    keep = nearest <= MAX_TEMPERATURE_GAP_S
    if not keep.any():
        raise UserInputError(f"--temperature {name}: no reading within {MAX_TEMPERATURE_GAP_S:g} s"
                             " of any calibration sample")  # fmt: skip
    return np.interp(t_s, t_th, value), keep


def unresolved_note(unresolved: int, total: int) -> str:
    """The warning for DUT samples left out by :func:`unresolved_field`."""
    return (f"{unresolved} of {total} DUT samples left out: the field changed faster than the"
            " reference's sample rate resolves there (a polarity flip, a ramp, a late command), so"
            " the field the DUT saw is unknown")  # fmt: skip


AXIS_INDEX = {"x": 0, "y": 1, "z": 2}


def lookup(results: dict[str, Any], result: str, path: str) -> float:
    """``results[result]`` then a dotted path (``springmann.a``, ``residual_rms_nt``); a part
    ``name[x]`` (or ``[0]``) takes one element of a per-axis list (``mounting_deg[z]``)."""
    if result not in results:
        raise KeyError(f"no result '{result}' (results so far: {', '.join(results) or 'none'})")
    value: Any = results[result]
    for part in path.split("."):
        name, _, index = part.partition("[")
        if not isinstance(value, dict) or name not in value:
            raise KeyError(f"result '{result}' has no '{path}'")
        value = value[name]
        if index:
            i = (
                AXIS_INDEX.get(index.rstrip("]"), -1)
                if not index[:-1].isdigit()
                else int(index[:-1])
            )
            if not index.endswith("]") or not isinstance(value, list) or not 0 <= i < len(value):
                raise KeyError(f"result '{result}' has no '{path}'")
            value = value[i]
    if not isinstance(value, int | float):
        raise KeyError(f"'{result}.{path}' is not a number")
    return float(value)


UNIT_SUFFIXES = (("_nt_per_rthz", "nT/rtHz"), ("_ut_per_a", "uT/A"), ("_deg", "deg"),
                 ("_ppm", "ppm"), ("_nt", "nT"), ("_ut", "uT"), ("_ma", "mA"), ("_hz", "Hz"),
                 ("_a", "A"), ("_v", "V"), ("_s", "s"))  # fmt: skip
"""Name endings and their units, longest first (``_ut_per_a`` before ``_a``)."""


def value_unit(path: str) -> str:
    """The unit of a result value from its dotted path, by the project's naming rule (units in
    names): ``residual_rms_nt`` -> nT, ``angular_uncertainty_deg.50_ut`` -> deg (the value is an
    angle; its key names the field it is for), ``springmann.a`` -> "" (a ratio)."""
    parts = path.split(".")
    for part in parts:  # the outermost named unit wins: a dict named *_deg holds angles
        for suffix, unit in UNIT_SUFFIXES:
            if part.endswith(suffix) and part != suffix.lstrip("_"):
                return unit
    return ""


def evaluate_criteria(results: dict[str, Any], criteria: list[dict[str, Any]]) -> dict[str, Any]:
    """PASS/FAIL per criterion with value, unit, limits and margin; the overall verdict."""
    rows = []
    for c in criteria:
        name = c.get("name") or f"{c['result']}.{c['value']}"
        try:
            value = lookup(results, c["result"], c["value"])
        except KeyError as exc:
            rows.append({"name": name, "verdict": Verdict.FAIL, "reason": str(exc).strip("'\"")})
            continue
        lo, hi = c.get("min"), c.get("max")
        expanded = expanded_uncertainty(results, c["result"], str(c["value"]))
        margins = [value - lo] if lo is not None else []
        margins += [hi - value] if hi is not None else []
        margin = min(margins) - (expanded or 0.0)
        row = {"name": name, "value": value, "unit": value_unit(str(c["value"])), "min": lo,
               "max": hi, "margin": margin, "verdict": Verdict.PASS if margin >= 0 else Verdict.FAIL}  # fmt: skip
        rows.append(row | ({} if expanded is None else {"uncertainty": expanded}))
    overall = (
        Verdict.PASS if rows and all(r["verdict"] == Verdict.PASS for r in rows) else Verdict.FAIL
    )
    rerun = timing_faults(results, criteria)
    verdict: dict[str, Any] = {"criteria": rows, "overall": RERUN if rerun else overall}
    if rerun:
        verdict["rerun"] = rerun
    return verdict


def expanded_uncertainty(results: dict[str, Any], result: str, path: str) -> float | None:
    """The expanded uncertainty (``COVERAGE_K`` times the combined 1-sigma of the uncertainty
    budget) of a judged value, None when its result has no budget for it: a criterion then passes
    only when the value is inside its limits by at least this (guarded acceptance, ILAC-G8)."""
    try:
        return COVERAGE_K * lookup(results, result, f"combined_sigma.{path}")
    except KeyError:
        return None


COVERAGE_K = 2.0
"""Coverage factor of the expanded uncertainty a criterion is judged with (about 95 %)."""
RERUN = Verdict.RERUN
"""The overall verdict of a run whose timing checks failed in a result a criterion judges: neither
PASS nor FAIL can be given from it (ADR 0020)."""


def timing_faults(results: dict[str, Any], criteria: list[dict[str, Any]]) -> list[dict[str, str]]:
    """[{result, why}] for each result the ``criteria`` judge whose data failed the timing
    checks (its ``timing_fault``): the steps to run again."""
    named = dict.fromkeys(str(c["result"]) for c in criteria)
    return [{"result": name, "why": str(results[name]["timing_fault"])} for name in named
            if isinstance(results.get(name), dict) and results[name].get("timing_fault")]  # fmt: skip
