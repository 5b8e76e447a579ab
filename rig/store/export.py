"""Exports of a stored run (the store stays the source of truth): CSV files or one HDF5 file."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from rig.store.run_store import RunReader


def export_csv(reader: RunReader, out_dir: Path) -> list[Path]:
    """``samples_<device>.csv``, ``channel_<name>.csv``, ``events.csv``, ``meta.json``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for device in reader.devices():
        path = out_dir / f"samples_{device}.csv"
        with path.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["t_s", "x_ut", "y_ut", "z_ut"])
            w.writerows(reader.samples(device))
        written.append(path)
    for name in reader.channel_names():
        path = out_dir / f"channel_{name}.csv"
        with path.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["t_s", "commanded_a", "measured_a"])
            w.writerows(reader.channel(name))
        written.append(path)
    path = out_dir / "events.csv"
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t_s", "level", "message"])
        w.writerows(reader.events())
    written.append(path)
    meta = out_dir / "meta.json"
    meta.write_text(
        json.dumps({"meta": reader.meta(), "results": reader.results()}, indent=2) + "\n"
    )
    written.append(meta)
    return written


def export_hdf5(reader: RunReader, path: Path) -> Path:
    """One HDF5 file: ``/samples/<device>`` (N x 4: t, x, y, z) and ``/channels/<name>``."""
    import h5py

    with h5py.File(path, "w") as f:
        f.attrs["meta"] = json.dumps(reader.meta())
        f.attrs["results"] = json.dumps(reader.results())
        for device in reader.devices():
            f.create_dataset(f"samples/{device}", data=np.array(reader.samples(device), float))
        for name in reader.channel_names():
            rows = [
                (t, np.nan if c is None else c, np.nan if m is None else m)
                for t, c, m in reader.channel(name)
            ]
            f.create_dataset(f"channels/{name}", data=np.array(rows, float))
    return path
