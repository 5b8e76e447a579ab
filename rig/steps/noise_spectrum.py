"""``noise_spectrum``: null the field, hold, and measure the DUT's noise spectral density
(nT/sqrt(Hz), one-sided) at 1 Hz and averaged over a band: the standard magnetometer noise figure.

The samples are put on a uniform time grid (the sampler's timestamps jitter by a few ms), each axis
is detrended and its density estimated by Welch's method (Hann window, 50 % overlap).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from rig import stored
from rig.analysis import settled_samples
from rig.characterization.stability import on_uniform_grid
from rig.errors import RigError
from rig.steps.base import Array, NullHoldKind, RunContext, SettledNeed, StepExecution
from rig.steps.vocabulary import ProcedureError, Step, StepParam

AROUND_1HZ = (0.8, 1.25)
"""The density 'at 1 Hz' is the mean over this band (Hz): one Welch bin is too noisy a figure."""
MIN_SAMPLES = 64


def amplitude_density(t_s: Array, xyz: Array) -> tuple[Array, Array, float]:
    """(frequencies Hz, amplitude spectral density per axis in input units / sqrt(Hz), shape
    (n_f, 3), sample rate Hz) of samples at times ``t_s`` (s), resampled to their median rate."""
    from scipy.signal import welch

    uniform, rate_hz = on_uniform_grid(t_s, xyz)
    nperseg = min(len(uniform), max(MIN_SAMPLES, int(2 ** np.ceil(np.log2(5.0 * rate_hz)))))
    f, psd = welch(uniform, fs=rate_hz, window="hann", nperseg=nperseg, detrend="linear", axis=0)
    return f, np.sqrt(psd), rate_hz


def band_mean(f: Array, asd: Array, band: tuple[float, float]) -> Array:
    """Per axis, the RMS of the density over ``band`` (Hz): power averaged, then its root."""
    sel = (f >= band[0]) & (f <= band[1])
    return np.asarray(np.sqrt(np.mean(asd[sel] ** 2, axis=0)))


@dataclass(frozen=True)
class NoiseSpectrumResult:
    """A noise spectrum's result: the DUT's amplitude spectral density (nT/rtHz, one-sided) at
    1 Hz (the mean over 0.8-1.25 Hz) and over ``band_hz``, worst axis and per axis (x, y, z)."""

    density_1hz_nt_per_rthz: float
    band_density_nt_per_rthz: float
    axis_density_1hz_nt_per_rthz: tuple[float, ...]
    axis_band_density_nt_per_rthz: tuple[float, ...]
    band_hz: tuple[float, float]
    """The band's low and high edge (Hz)."""
    rate_hz: float
    """The samples' median rate (Hz), the grid they were put on."""
    samples: int
    """Settled samples used."""
    device: str
    """The magnetometer measured (its rig configuration name)."""
    settle_s: float
    """Samples this long (s) after a field or load change were left out."""

    def to_dict(self) -> dict[str, Any]:
        """The stored mapping."""
        return {
            "density_1hz_nt_per_rthz": self.density_1hz_nt_per_rthz,
            "band_density_nt_per_rthz": self.band_density_nt_per_rthz,
            "axis_density_1hz_nt_per_rthz": list(self.axis_density_1hz_nt_per_rthz),
            "axis_band_density_nt_per_rthz": list(self.axis_band_density_nt_per_rthz),
            "band_hz": list(self.band_hz), "rate_hz": self.rate_hz, "samples": self.samples,
            "device": self.device, "settle_s": self.settle_s,
        }  # fmt: skip

    @classmethod
    def from_dict(cls, d: Any) -> NoiseSpectrumResult:
        """Read a stored noise spectrum result; a :class:`StoredResultError` names what is wrong."""
        what = "noise spectrum result"
        d = stored.mapping(d, what)
        lo, hi = stored.numbers(d, "band_hz", what, 2)
        return cls(
            stored.number(d, "density_1hz_nt_per_rthz", what),
            stored.number(d, "band_density_nt_per_rthz", what),
            stored.numbers(d, "axis_density_1hz_nt_per_rthz", what, 3),
            stored.numbers(d, "axis_band_density_nt_per_rthz", what, 3),
            (lo, hi),
            stored.number(d, "rate_hz", what),
            stored.integer(d, "samples", what),
            stored.text(d, "device", what),
            stored.number(d, "settle_s", what),
        )


def read_noise_spectrum(result: Any) -> NoiseSpectrumResult | None:
    """A stored result as a noise spectrum; None when it is not one (the report then lists the
    result's numbers, as for any result its kind does not describe)."""
    return stored.read_or_none(NoiseSpectrumResult.from_dict, result)


class NoiseSpectrum(NullHoldKind):
    name = "noise_spectrum"
    summary = "DUT noise spectral density in a nulled field (nT/rtHz at 1 Hz and over a band)"
    result_values = ("density_1hz_nt_per_rthz", "band_density_nt_per_rthz", "rate_hz", "samples",
                     "settle_s")  # fmt: skip
    params: ClassVar[dict[str, StepParam]] = {
        "hold_s": StepParam("float", 20.0, 5.0, 86400.0),
        "band_hz": StepParam("range2", [0.1, 5.0], 0.001, 10000.0),
        "trim": StepParam("str", "no", choices=("yes", "no")),
        "settle_s": StepParam("float", 0.5, 0.0, 60.0),
        "magnetometer": StepParam("str", "dut"),
    }

    def validate(self, params: dict[str, Any], loads: tuple[str, ...], where: str) -> None:
        lo, hi = params["band_hz"]
        if not lo < hi:
            raise ProcedureError(f"{where}: band_hz must be [low, high] with low < high")
        if params["hold_s"] < 4.0 / lo:
            raise ProcedureError(
                f"{where}: hold_s must cover 4 periods of the band's low edge ({4.0 / lo:g} s for {lo:g} Hz)"
            )

    def settled_need(self, step: Step, magnetometers: Mapping[str, str]) -> SettledNeed:
        device = magnetometers.get(step.params["magnetometer"], step.params["magnetometer"])
        return SettledNeed((device,), MIN_SAMPLES, float(step.params["settle_s"]))

    def execution(self, ctx: RunContext, step: Step) -> StepExecution:
        return MeasureSpectrum(ctx, step)

    def figures(self, reader: Any, name: str, result: Any, plt: Any) -> list[tuple[str, Any]]:
        window = next(((t0, t1) for _, n, _, t0, t1 in reader.steps() if n == name and t1), None)
        found = read_noise_spectrum(result)
        if window is None or found is None:
            return []
        rows = settled_samples(reader, found.device, window, found.settle_s)
        if len(rows) < MIN_SAMPLES:
            return []
        f, asd, _ = amplitude_density(rows[:, 0], rows[:, 1:])
        fig, ax = plt.subplots(figsize=(7.0, 3.6))
        for i, axis in enumerate("xyz"):
            ax.loglog(f[1:], 1000.0 * asd[1:, i], lw=0.9, label=axis)
        lo, hi = found.band_hz
        ax.axvspan(lo, hi, color="0.9", zorder=0, label="band")
        ax.axhline(found.band_density_nt_per_rthz, color="k", ls="--", lw=0.8,
                   label=f"band mean {found.band_density_nt_per_rthz:.3g} nT/rtHz")  # fmt: skip
        ax.set_xlabel("frequency (Hz)")
        ax.set_ylabel("noise density (nT/rtHz)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))  # beside the axes
        return [(f"Noise spectrum '{name}'", fig)]

    def report_lines(self, name: str, result: Any) -> list[str]:
        found = read_noise_spectrum(result)
        if found is None:
            return []
        lo, hi = found.band_hz
        return [
            f"Noise spectrum {name}: {found.density_1hz_nt_per_rthz:.3g} nT/rtHz"
            f" at 1 Hz, {found.band_density_nt_per_rthz:.3g} nT/rtHz over {lo:g}-{hi:g} Hz"
            f" ({found.samples} samples at {found.rate_hz:.1f} Hz, worst axis)."
        ]


class MeasureSpectrum(StepExecution):
    def finish(self, t_start: float, t_end: float) -> None:
        p = self.step.params
        device = self.ctx.proc.magnetometers.get(p["magnetometer"], p["magnetometer"])
        reader = self.ctx.open_reader()
        try:
            rows = settled_samples(reader, device, (t_start, t_end), p["settle_s"])
        finally:
            reader.close()
        if len(rows) < MIN_SAMPLES:
            raise RigError(
                f"noise_spectrum '{self.step.name}': only {len(rows)} settled samples of '{device}'"
                f" (at least {MIN_SAMPLES}): lengthen hold_s"
            )
        f, asd, rate_hz = amplitude_density(rows[:, 0], rows[:, 1:])
        lo, hi = p["band_hz"]
        if hi > rate_hz / 2:
            raise RigError(
                f"noise_spectrum '{self.step.name}': band_hz reaches {hi:g} Hz, above half the"
                f" {rate_hz:.1f} Hz sample rate: lower the band's high edge"
            )
        at_1hz = 1000.0 * band_mean(f, asd, AROUND_1HZ)
        band = 1000.0 * band_mean(f, asd, (lo, hi))
        result = NoiseSpectrumResult(
            float(at_1hz.max()), float(band.max()), tuple(at_1hz.tolist()), tuple(band.tolist()),
            (lo, hi), rate_hz, len(rows), device, p["settle_s"],
        )  # fmt: skip
        self.ctx.record_result(self.step.name, result.to_dict())


KIND = NoiseSpectrum()
