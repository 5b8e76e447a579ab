"""Exports of a stored run (the store stays the source of truth): CSV files or one HDF5 file.

Time base: the store timestamps everything with the rig's monotonic clock (``t_s``, seconds since
the computer booted). The run's meta holds ``start_time`` (UTC, ISO 8601, milliseconds; whole
seconds in runs recorded before 2026-11-23) and ``start_monotonic`` (the monotonic clock at the same
moment), so

    t_run_s = t_s - start_monotonic                  (exact: seconds since the run started)
    t_utc   = start_time + (t_s - start_monotonic)    (ISO 8601; as good as the computer's clock)

``samples_aligned.csv`` (``/aligned`` in HDF5) puts the DUT and every other magnetometer on the DUT's
timestamps (linear interpolation, empty across gaps), with the load currents in force at each.
"""

from __future__ import annotations

import csv
import datetime as dt
import json
import math
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from rig.store import safe_files
from rig.store.run_store import RunReader

Array = npt.NDArray[np.float64]

MAX_GAP_PERIODS = 3.0
"""An interpolated value needs neighbours at most this many median sample periods apart."""


class TimeBase:
    """Converts the store's monotonic timestamps to seconds since run start and to UTC."""

    def __init__(self, meta: dict[str, Any]) -> None:
        start_mono = meta.get("start_monotonic")
        self.start_monotonic = float(start_mono) if isinstance(start_mono, int | float) else None
        try:
            start = dt.datetime.fromisoformat(str(meta.get("start_time")))
        except ValueError:
            start = None
        if start is not None and start.tzinfo is None:
            start = start.replace(tzinfo=dt.UTC)
        self.start_utc = start

    def run_s(self, t: Array) -> Array:
        """Seconds since the run started (NaN without ``start_monotonic``)."""
        if self.start_monotonic is None:
            return np.full(len(t), np.nan)
        return np.asarray(t, float) - self.start_monotonic

    def utc(self, t: Array) -> list[str]:
        """ISO 8601 UTC with milliseconds ('' without a start time)."""
        if self.start_utc is None or self.start_monotonic is None:
            return [""] * len(t)
        start, mono = self.start_utc, self.start_monotonic
        return [
            (start + dt.timedelta(milliseconds=round(1000.0 * (float(x) - mono))))
            .astimezone(dt.UTC)
            .isoformat(timespec="milliseconds")
            .replace("+00:00", "Z")
            for x in t
        ]

    def describe(self) -> dict[str, Any]:
        """The time base as written to ``meta.json`` and the HDF5 attributes."""
        return {
            "t_s": "monotonic clock of the rig computer (s); every table's original time column",
            "start_monotonic_s": self.start_monotonic,
            "start_time_utc": self.start_utc.isoformat() if self.start_utc else None,
            "t_run_s": "t_s - start_monotonic_s: seconds since the run started",
            "t_utc": "start_time_utc + t_run_s, ISO 8601",
        }


def _interpolate(t: Array, ts: Array, values: Array) -> Array:
    """``values`` (N x 3 at times ``ts``) at times ``t``; NaN outside the recorded span and where
    the neighbouring samples are further apart than :data:`MAX_GAP_PERIODS` median periods."""
    out = np.full((len(t), values.shape[1]), np.nan)
    if len(ts) == 0:
        return out
    if len(ts) == 1:
        out[t == ts[0]] = values[0]
        return out
    for j in range(values.shape[1]):
        out[:, j] = np.interp(t, ts, values[:, j], left=np.nan, right=np.nan)
    steps = np.diff(ts)
    steps = steps[steps > 0]
    if len(steps) == 0:
        return out
    right = np.clip(np.searchsorted(ts, t, side="right"), 1, len(ts) - 1)
    left = right - 1
    exact = (ts[left] == t) | (ts[right] == t)
    too_far = (ts[right] - ts[left] > MAX_GAP_PERIODS * float(np.median(steps))) & ~exact
    out[too_far] = np.nan
    return out


def _hold(t: Array, ts: Array, values: Array) -> Array:
    """The last value at or before each of ``t`` (NaN before the first): a commanded current
    holds until the next command."""
    out = np.full(len(t), np.nan)
    if len(ts) == 0:
        return out
    idx = np.searchsorted(ts, t, side="right") - 1
    ok = idx >= 0
    out[ok] = values[idx[ok]]
    return out


def aligned_columns(reader: RunReader) -> dict[str, Any] | None:
    """The DUT's samples with every other magnetometer interpolated to the DUT's timestamps and the
    procedure's load currents (commanded, last measured) in force at each; ``None`` when the run
    has no DUT samples. Columns: ``t_utc``, ``t_run_s``, ``t_s``, ``dut_{x,y,z}_ut``,
    ``reference_{x,y,z}_ut`` (or ``<device>_...`` for magnetometers without a role),
    ``<load>_commanded_a``, ``<load>_measured_a``."""
    meta = reader.meta()
    roles = meta.get("magnetometers") or {"dut": "dut", "reference": "reference"}
    devices = reader.devices()
    dut = roles.get("dut")
    if dut not in devices:
        return None
    rows = np.array(reader.samples(dut), float).reshape(-1, 4)
    t = rows[:, 0]
    base = TimeBase(meta)
    cols: dict[str, Any] = {"t_utc": base.utc(t), "t_run_s": base.run_s(t), "t_s": t}
    for ax, name in enumerate("xyz"):
        cols[f"dut_{name}_ut"] = rows[:, 1 + ax]
    label = {dev: role for role, dev in roles.items() if role != "dut"}
    for dev in devices:
        if dev == dut:
            continue
        other = np.array(reader.samples(dev), float).reshape(-1, 4)
        values = _interpolate(t, other[:, 0], other[:, 1:])
        prefix = label.get(dev, dev)
        if f"{prefix}_x_ut" in cols:  # a device named like a role
            prefix = f"device_{dev}"
        for ax, name in enumerate("xyz"):
            cols[f"{prefix}_{name}_ut"] = values[:, ax]
    for ch in meta.get("loads") or []:
        for kind in ("commanded", "measured"):
            ts, vs = _column(reader, ch, kind)
            cols[f"{ch}_{kind}_a"] = _hold(t, ts, vs)
    for name in meta.get("thermometers") or []:
        ts, vs = _column(reader, name, "measured")
        cols[f"{name}_c"] = _interpolate(t, ts, vs.reshape(-1, 1))[:, 0]
    return cols


def _column(
    reader: RunReader, name: str, column: Literal["commanded", "measured"]
) -> tuple[Array, Array]:
    """Times and values (arrays) of a channel's ``column``, where it has one."""
    rows = np.array(reader.channel_column(name, column), float).reshape(-1, 2)
    return rows[:, 0], rows[:, 1]


def channel_unit(meta: dict[str, Any], name: str) -> str:
    """The unit suffix of a stored channel: ``c`` (degrees C) for a thermometer, else ``a``."""
    return "c" if name in (meta.get("thermometers") or []) else "a"


def _cell(v: Any) -> Any:
    if isinstance(v, float | np.floating):
        return "" if math.isnan(v) else repr(float(v))
    return v


def _file_name(name: str) -> str:
    """A device or channel name as part of one file name: no folder separator, no NUL."""
    return name.replace("/", "_").replace("\\", "_").replace("\x00", "_")


def export_csv(reader: RunReader, out_dir: Path) -> list[Path]:
    """``samples_<device>.csv``, ``channel_<name>.csv``, ``events.csv`` (all with the original
    monotonic ``t_s``), ``samples_aligned.csv`` (when the run has DUT samples: UTC, seconds since
    run start, DUT and reference on one time base, load currents, thermometers in degrees C) and
    ``meta.json`` (with the time base). Every file replaces its name, never writing through a
    link; a linked ``out_dir`` is refused."""
    out_dir.mkdir(parents=True, exist_ok=True)
    safe_files.check_folder(out_dir)
    written = []
    for device in reader.devices():
        path = out_dir / _file_name(f"samples_{device}.csv")
        with safe_files.writing(path, newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["t_s", "x_ut", "y_ut", "z_ut", "t_unc_s"])
            w.writerows([_cell(v) for v in row] for row in reader.dated_samples(device))
        written.append(path)
    meta_values = reader.meta()
    for name in reader.channel_names():
        path = out_dir / _file_name(f"channel_{name}.csv")
        unit = channel_unit(meta_values, name)
        with safe_files.writing(path, newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["t_s", f"commanded_{unit}", f"measured_{unit}"])
            w.writerows(reader.channel(name))
        written.append(path)
    path = out_dir / "events.csv"
    with safe_files.writing(path, newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t_s", "level", "message"])
        w.writerows(reader.events())
    written.append(path)
    cols = aligned_columns(reader)
    if cols is not None:
        path = out_dir / "samples_aligned.csv"
        with safe_files.writing(path, newline="") as fh:
            w = csv.writer(fh)
            w.writerow(list(cols))
            for row in zip(*cols.values(), strict=True):
                w.writerow([_cell(v) for v in row])
        written.append(path)
    meta = out_dir / "meta.json"
    safe_files.write_text(
        meta,
        json.dumps(
            {
                "meta": reader.meta(),
                "results": reader.results(),
                "time_base": TimeBase(reader.meta()).describe(),
            },
            indent=2,
        )
        + "\n",
    )
    written.append(meta)
    return written


def export_hdf5(reader: RunReader, path: Path) -> Path:
    """One HDF5 file: ``/samples/<device>`` (N x 4: t_s, x, y, z) and ``/channels/<name>`` (N x 3:
    t_s, commanded, measured) as stored; ``/time/samples/<device>/{t_run_s,t_utc}`` and
    ``/time/channels/<name>/...`` for each row; ``/aligned/<column>`` as ``samples_aligned.csv``.
    Root attributes ``meta``, ``results``, ``time_base`` (JSON). Written beside ``path`` and
    renamed over it: a link at ``path`` is replaced, its target left alone."""
    with safe_files.replacing(path) as tmp:
        _write_hdf5(reader, tmp)
    return path


def _write_hdf5(reader: RunReader, path: Path) -> None:
    import h5py

    meta = reader.meta()
    base = TimeBase(meta)
    text = h5py.string_dtype()
    with h5py.File(path, "w") as f:
        f.attrs["meta"] = json.dumps(meta)
        f.attrs["results"] = json.dumps(reader.results())
        f.attrs["time_base"] = json.dumps(base.describe())
        for device in reader.devices():
            dated = np.array(reader.dated_samples(device), float).reshape(-1, 5)
            data = dated[:, :4]
            ds = f.create_dataset(f"samples/{device}", data=data)
            ds.attrs["columns"] = "t_s,x_ut,y_ut,z_ut"
            f.create_dataset(f"time/samples/{device}/t_run_s", data=base.run_s(data[:, 0]))
            f.create_dataset(f"time/samples/{device}/t_unc_s", data=dated[:, 4])
            f.create_dataset(f"time/samples/{device}/t_utc", data=base.utc(data[:, 0]), dtype=text)
        for name in reader.channel_names():
            rows = [
                (t, np.nan if c is None else c, np.nan if m is None else m)
                for t, c, m in reader.channel(name)
            ]
            data = np.array(rows, float).reshape(-1, 3)
            ds = f.create_dataset(f"channels/{name}", data=data)
            unit = channel_unit(meta, name)
            ds.attrs["columns"] = f"t_s,commanded_{unit},measured_{unit}"
            f.create_dataset(f"time/channels/{name}/t_run_s", data=base.run_s(data[:, 0]))
            f.create_dataset(f"time/channels/{name}/t_utc", data=base.utc(data[:, 0]), dtype=text)
        cols = aligned_columns(reader)
        if cols is not None:
            for key, values in cols.items():
                if key == "t_utc":
                    f.create_dataset(f"aligned/{key}", data=values, dtype=text)
                else:
                    f.create_dataset(f"aligned/{key}", data=np.asarray(values, float))
