"""The DUT's offset at rest, as the steps that hold a null field measure it (stability, perming,
thermal_cycle): its settled samples in a window, corrected by the run's latest calibration when
there is one, less a reference magnetometer's settled samples interpolated to the same times."""

from __future__ import annotations

from dataclasses import dataclass

from rig.analysis import offsets_less_reference, settled_samples
from rig.calibration.record import latest_calibration
from rig.steps.base import Array, RunContext


@dataclass(frozen=True)
class AtRest:
    """Times (s, monotonic) and the DUT's offsets there (nT, (N, 3)); whether a calibration of
    the run corrected them."""

    t_s: Array
    offsets_nt: Array
    calibrated: bool


def offsets_at_rest(ctx: RunContext, dut: str, reference: str | None,
                    windows: list[tuple[float, float]], settle_s: float,
                    certified: bool = True) -> list[AtRest]:  # fmt: skip
    """Per window (monotonic s) the DUT's offsets less ``reference`` (None: nothing subtracted;
    ``certified``: through the reference's certificate, the cage's reference; an outside one
    as it reads), its samples ``settle_s`` clear of every field and load change."""
    latest = latest_calibration(ctx.results)
    correction = latest[1].correction if latest is not None else None
    reader = ctx.open_reader()
    try:
        out = []
        for window in windows:
            rows = settled_samples(reader, dut, window, settle_s)
            ref = settled_samples(reader, reference, window, settle_s) if reference else None
            t, offsets = offsets_less_reference(rows, ref, correction,
                                                ctx.correction if certified else None)  # fmt: skip
            out.append(AtRest(t, offsets, latest is not None))
        return out
    finally:
        reader.close()
