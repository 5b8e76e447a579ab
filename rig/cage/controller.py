"""The cage controller: field commands to currents, ramps, polarity, trim, null and safe state.

Every current the controller sends comes from :func:`rig.cage.limits.plan_ramp`, so the per-axis
current limit and the slew limit hold for every command; the drivers check their own ranges again.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

import timebase
from drivers.protocols import SupplyReading
from rig.cage.limits import CageLimitError, CageLimits, plan_ramp
from rig.cage.model import CageModel
from rig.errors import RigError

SENT_KEPT = 10_000
"""How many of the latest set-point vectors the controller keeps in memory."""
SAFE_TIMEOUT_S = 5.0
"""Longest wait for one supply to confirm it is off (a dead link gives up sooner)."""

Array = npt.NDArray[np.float64]


class CurrentSource(Protocol):
    """A supply driving one coil (unipolar, or bipolar with a signed set-point)."""

    def set_voltage(self, volts: float) -> float: ...
    def set_current(self, amps: float) -> float: ...
    def set_output(self, on: bool) -> None: ...
    def safe(self) -> None: ...
    def read(self) -> SupplyReading: ...


class Polarity(Protocol):
    """H-bridge relays, one per axis."""

    def set_polarity(self, axis: int, sign: int) -> None: ...


class FieldSensor(Protocol):
    """A magnetometer returning (x, y, z) in uT."""

    def read(self) -> tuple[float, float, float]: ...


@dataclass
class AxisDrive:
    """One coil axis: its supply, how polarity is made, the supply's compliance voltage (V) and a
    read-back of the actual output current (A, unsigned) used for break-before-make."""

    supply: CurrentSource
    bipolar: bool
    compliance_v: float
    output_current: Callable[[], float] | None = None


@dataclass(frozen=True)
class TrimResult:
    """Outcome of a closed-loop trim."""

    currents_a: Array
    measured_ut: Array
    error_nt: float
    iterations: int
    settled: bool


class CageController:
    """Drives three coil axes so that the field at the DUT follows commands, within limits."""

    def __init__(
        self,
        axes: list[AxisDrive],
        model: CageModel,
        limits: CageLimits,
        *,
        relays: Polarity | None = None,
        reference: FieldSensor | None = None,
        reference_to_cage: tuple[Array, Array] | None = None,
        sleep: Callable[[float], None] = timebase.sleep,
        zero_threshold_a: float = 0.02,
    ) -> None:
        if len(axes) != 3:
            raise ValueError("a cage has three axes")
        if any(not a.bipolar for a in axes) and relays is None:
            raise RigError("unipolar coil supplies need polarity relays in the rig configuration")
        self.axes = axes
        self.model = model
        self.limits = limits
        self.relays = relays
        self.reference = reference
        self.reference_to_cage = reference_to_cage
        self.sleep = sleep
        self.zero_threshold_a = zero_threshold_a
        self.currents = np.zeros(3)
        self.signs = [1, 1, 1]
        # the latest set-point vectors sent, for audit and tests; bounded, as an orbit replay sends
        # 72 000 an hour (the store keeps every one as coil channel rows)
        self.sent: deque[Array] = deque(maxlen=SENT_KEPT)
        self.last_send_s: float | None = None
        self.enabled = False

    # --- outputs --------------------------------------------------------------------------------

    def enable(self) -> None:
        """Set-points to zero at the compliance voltage, outputs on, relays normal."""
        for axis, drive in enumerate(self.axes):
            drive.supply.set_current(0.0)
            drive.supply.set_voltage(drive.compliance_v)
            if not drive.bipolar and self.relays is not None:
                self.relays.set_polarity(axis, 1)
            drive.supply.set_output(True)
        self.currents = np.zeros(3)
        self.signs = [1, 1, 1]
        self.enabled = True

    def _send(self, point: Array) -> None:
        for axis, drive in enumerate(self.axes):
            value = float(point[axis])
            if value == self.currents[axis]:
                continue
            if drive.bipolar:
                drive.supply.set_current(value)
                continue
            sign = -1 if value < 0 else 1
            if value != 0.0 and sign != self.signs[axis]:
                self._flip(axis, sign)
            drive.supply.set_current(abs(value))
        self.currents = point.copy()
        self.sent.append(point.copy())
        self.last_send_s = timebase.monotonic()

    def _flip(self, axis: int, sign: int) -> None:
        """Break before make: wait for the coil current to decay, then switch the relay."""
        if self.currents[axis] != 0.0:
            raise CageLimitError(
                f"axis {'xyz'[axis]}: polarity change requested at non-zero set-point"
            )
        self._await_decay(axis, self.sleep)
        assert self.relays is not None
        self.relays.set_polarity(axis, sign)
        self.signs[axis] = sign

    def _await_decay(self, axis: int, sleep: Callable[[float], None]) -> None:
        """Wait (at most 2 s) for the coil current of ``axis`` to fall below the zero threshold."""
        output_current = self.axes[axis].output_current
        if output_current is None:
            return
        deadline = timebase.monotonic() + 2.0
        while output_current() > self.zero_threshold_a:
            if timebase.monotonic() > deadline:
                raise RigError(
                    f"axis {'xyz'[axis]}: coil current did not decay below"
                    f" {self.zero_threshold_a:g} A within 2 s; check the supply"
                )
            sleep(0.01)

    def set_currents(
        self, target_a: npt.ArrayLike, *, sleep: Callable[[float], None] | None = None
    ) -> Array:
        """Ramp to signed coil currents (A) within the limits; returns the currents set. Waits
        between set-points with ``sleep`` (default: the controller's, which may raise a fault)."""
        if not self.enabled:
            self.enable()
        wait = self.sleep if sleep is None else sleep
        target = np.asarray(target_a, float)
        for point in plan_ramp(self.currents, target, self.limits):
            self._send(point)
            wait(self.limits.step_s)
        return self.currents.copy()

    def set_field(self, field_ut: npt.ArrayLike) -> Array:
        """Ramp to the currents the model gives for ``field_ut`` (uT, cage frame)."""
        field = np.asarray(field_ut, float)
        self.limits.check_field(field, "set_field")
        currents = self.model.currents_a(field)
        self.limits.check_currents(currents, f"field {np.round(field, 2).tolist()} uT")
        return self.set_currents(currents)

    def track(self, field_ut: npt.ArrayLike) -> bool:
        """Follow a slowly changing field (orbit replay): one set-point, no ramp, when the change
        fits within the slew limit for the time since the last set-point; otherwise a ramp. An
        axis changing sign behind relays always ramps through zero (break before make). Returns
        whether it ramped (the field then passed through values that were not asked for)."""
        field = np.asarray(field_ut, float)
        self.limits.check_field(field, "track")
        currents = self.model.currents_a(field)
        self.limits.check_currents(currents, f"field {np.round(field, 2).tolist()} uT")
        if not self.enabled:
            self.enable()
        elapsed = (
            self.limits.step_s
            if self.last_send_s is None
            else timebase.monotonic() - self.last_send_s
        )
        allowed = self.limits.step_within_a(elapsed)
        flips = [
            ax for ax, d in enumerate(self.axes)
            if not d.bipolar and currents[ax] != 0 and (1 if currents[ax] > 0 else -1) != self.signs[ax]
            and self.currents[ax] != 0
        ]  # fmt: skip
        change = float(np.max(np.abs(currents - self.currents)))
        if not flips and change <= self.limits.max_step_a:
            if change > allowed:  # too soon after the last set-point: wait the slew out
                self.sleep(self._wait_for_step_s(change, elapsed))
            self._send(currents)
            return False
        self.set_currents(currents)
        return True

    def _wait_for_step_s(self, change_a: float, elapsed_s: float) -> float:
        """How much longer (s) than ``elapsed_s`` to wait before a set-point change of
        ``change_a`` keeps the coil current's slope within the slew limit."""
        lim = self.limits
        if lim.coil_tau_s is None:
            return (change_a - lim.step_within_a(elapsed_s)) / lim.max_slew_a_per_s
        fraction = change_a / (lim.max_slew_a_per_s * lim.coil_tau_s)
        if fraction >= 1.0:  # beyond any wait: one ramp step (max_step_a) at most, checked above
            return lim.step_s
        return max(0.0, -lim.coil_tau_s * math.log1p(-fraction) - elapsed_s)

    def safe(self, relays: bool = True) -> list[str]:
        """Ramp to zero if possible, then every output off, then (``relays``) the polarity relays
        to normal once their coils have decayed; never raises. Returns problems seen."""
        problems: list[str] = []
        dead = any(getattr(getattr(d.supply, "link", None), "failed", False) for d in self.axes)
        if self.enabled and not dead:  # with a supply not answering, switch off at once
            try:  # plain sleeps: the fault that brought us here must not stop the ramp down
                self.set_currents(np.zeros(3), sleep=timebase.sleep)
            except Exception as exc:  # a dead link must not stop the others going safe
                problems.append(f"ramp to zero failed: {exc}")

        def off(axis: int, drive: AxisDrive) -> None:
            try:
                drive.supply.safe()
            except Exception as exc:
                problems.append(f"axis {'xyz'[axis]} supply: {exc}")

        # in parallel: a supply that does not answer must not delay the others
        threads = [timebase.Thread(off, args=(i, d), name=f"safe-{'xyz'[i]}")
                   for i, d in enumerate(self.axes)]  # fmt: skip
        for t in threads:
            t.start()
        for t in threads:
            t.join(SAFE_TIMEOUT_S)
        self.enabled = False
        self.currents = np.zeros(3)
        if relays:
            problems += self.relays_normal()
        return problems

    def relays_normal(self) -> list[str]:
        """Reversed relays back to normal once their coil's current has decayed; problems."""
        problems: list[str] = []
        for axis, drive in enumerate(self.axes):
            if drive.bipolar or self.relays is None or self.signs[axis] == 1:
                continue
            try:
                self._await_decay(axis, timebase.sleep)
                self.relays.set_polarity(axis, 1)
                self.signs[axis] = 1
            except Exception as exc:  # a relay left reversed is reported, the rest goes on
                problems.append(f"axis {'xyz'[axis]} polarity relay left reversed: {exc}")
        return problems

    def instruments(self) -> dict[str, str]:
        """Identity of every instrument that can say it (model, serial, firmware), for records."""
        found: dict[str, str] = {}
        named: list[tuple[str, object]] = [
            (f"coil_{'xyz'[i]}", a.supply) for i, a in enumerate(self.axes)
        ]
        named += [("polarity", self.relays), ("reference", self.reference)]
        for role, device in named:
            identify = getattr(device, "identify", None)
            if identify is None or (
                role == "reference" and getattr(device, "fmt", None) is not None
            ):
                continue  # a line-oriented sensor identifies only by reading a sample
            try:
                ident = identify()
            except Exception as exc:  # a record, not a check: note the failure and go on
                found[role] = f"unidentified ({exc})"
                continue
            found[role] = " ".join(p for p in (ident.model, ident.serial and f"SN {ident.serial}",
                                                ident.firmware and f"FW {ident.firmware}") if p)  # fmt: skip
        return found

    # --- measurement ----------------------------------------------------------------------------

    def measure_ut(self, samples: int = 10, *, fresh: bool = True) -> Array:
        """Mean of ``samples`` consecutive reference readings, in the cage frame (uT).

        ``fresh`` discards what a streaming sensor buffered before this call (readings from
        before the last command).
        """
        return self.to_cage(np.mean(self.reference_readings(samples, fresh=fresh), axis=0))

    def to_cage(self, raw: npt.ArrayLike) -> Array:
        """A raw reference reading (uT, its own frame) in the cage frame by its certificate
        (unchanged without one)."""
        raw = np.asarray(raw, float)
        if self.reference_to_cage is not None:
            matrix, offset = self.reference_to_cage
            return np.asarray(matrix @ (raw - offset))
        return np.asarray(raw)

    def reference_readings(self, samples: int, *, fresh: bool = True) -> Array:
        """``samples`` consecutive raw reference readings ((N, 3) uT, the sensor's own frame,
        uncorrected); ``fresh`` as for :meth:`measure_ut`."""
        if self.reference is None:
            raise RigError(
                "no reference magnetometer configured: trim and characterization need one"
            )
        flush = getattr(self.reference, "flush", None)
        if fresh and flush is not None:
            flush()
            self.reference.read()  # a sample taken before the flush may still be on its way
        readings = []
        for _ in range(samples):
            self.sleep(0)  # a fault reported meanwhile ends the measurement
            readings.append(self.reference.read())
        return np.asarray(readings, float)

    def wait_settled(
        self,
        target_ut: Array,
        tolerance_nt: float,
        settle_s: float,
        timeout_s: float,
        average_n: int = 10,
    ) -> bool:
        """True once the running mean of ``average_n`` reference samples has stayed within
        ``tolerance_nt`` of the target for ``settle_s`` without interruption."""
        recent: deque[Array] = deque(maxlen=average_n)
        start = timebase.monotonic()
        inside_since: float | None = None
        fresh = True
        while timebase.monotonic() - start < timeout_s:
            recent.append(self.measure_ut(1, fresh=fresh))
            fresh = False  # consecutive samples from here on, so mains ripple averages out
            now = timebase.monotonic()
            if len(recent) < average_n:
                continue
            err_nt = 1000.0 * float(np.linalg.norm(np.mean(recent, axis=0) - target_ut))
            if err_nt > tolerance_nt:
                inside_since = None
                continue
            inside_since = now if inside_since is None else inside_since
            if now - inside_since >= settle_s:
                return True
        return False

    def trim(
        self,
        target_ut: npt.ArrayLike,
        *,
        tolerance_nt: float = 10.0,
        settle_s: float = 0.5,
        samples: int = 10,
        max_iterations: int = 8,
        transient_s: float = 0.2,
    ) -> TrimResult:
        """Closed loop on the reference: correct the currents by ``K^-1 (target - measured)``
        until the averaged error is within half of ``tolerance_nt``, then confirm the field stays
        within ``tolerance_nt`` for ``settle_s`` ("within X nT for Y s"). A correction whose
        field by the cage model is beyond the field limit is refused (CageLimitError)."""
        target = np.asarray(target_ut, float)
        self.set_field(target)
        measured = target
        err = np.inf
        iteration = 0
        for iteration in range(1, max_iterations + 1):
            self.sleep(transient_s)
            measured = self.measure_ut(samples)
            err = 1000.0 * float(np.linalg.norm(target - measured))
            # Aim for half the tolerance, so that measurement noise does not leave the true field
            # sitting on the edge; accept anything within the tolerance once iterations run out.
            if err <= 0.5 * tolerance_nt or iteration == max_iterations:
                break
            correction = np.linalg.solve(self.model.k_ut_per_a, target - measured)
            trimmed = self.currents + correction
            # the trim answers to the field limit as a whole, not only to each axis's current:
            # a reference reading wrong (a bad certificate) must not trim the field past it
            self.limits.check_field(self.model.field_ut(trimmed),
                                    f"trim to {np.round(target, 2).tolist()} uT")  # fmt: skip
            self.set_currents(trimmed)
        if err <= tolerance_nt:
            settled = self.wait_settled(target, tolerance_nt, settle_s, timeout_s=4 * settle_s + 2)
            return TrimResult(self.currents.copy(), measured, err, iteration, settled)
        return TrimResult(self.currents.copy(), measured, err, iteration, False)
