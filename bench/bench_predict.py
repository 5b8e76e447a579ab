"""How fast is ``rig check --predict``? A 1000-step procedure predicted, against the dry run of the
same procedure (``rig check`` alone) measured in the same process: the figure is the ratio and
the prediction's own seconds (goal: under 1 s for 1000 steps on this machine).

The procedure: 996 ``set_field`` holds of 1.5 s at fields spread over the sphere (15-45 uT), the
two load channels stepping through their levels in every fourth hold, a ``null_field`` at the
start, then a vector and a scalar ``calibrate`` with both channels and a ``check`` on their sigmas:
about 34,000 planned DUT samples. Each figure is the median of ``--repeats`` runs.

Run: ``nice .venv/bin/python bench/bench_predict.py [--steps 1000] [--repeats 5]``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def procedure_text(steps: int) -> str:
    """A procedure of ``steps`` steps (see the module's docstring)."""
    from rig.steps.geometry import fibonacci_directions

    holds = steps - 4
    fields = fibonacci_directions(holds) * np.linspace(15.0, 45.0, holds)[:, None]
    lines = ["procedure: Long", "magnetometers: {dut: dut, reference: reference}",
             "loads: [load_bus, load_panel]", "steps:", "  - null_field: {hold_s: 4}",
             "    name: floor"]  # fmt: skip
    for i, f in enumerate(fields):
        lines.append(
            f"  - set_field: {{field_ut: [{f[0]:.3f}, {f[1]:.3f}, {f[2]:.3f}], hold_s: 1.5}}"
        )
        lines.append(f"    name: hold {i}")
        if i % 4 == 0:
            lines += ["    loads:", f"      load_bus: {{constant: {{current_a: {0.4 * (i % 5)}}}}}",
                      f"      load_panel: {{constant: {{current_a: {0.5 * (i % 3)}}}}}"]  # fmt: skip
    for model in ("vector", "scalar"):
        lines += [f"  - calibrate: {{model: {model}, telemetry: [load_bus, load_panel]}}",
                  f"    name: {model} fit"]  # fmt: skip
    lines += ["  - check:", "      criteria:",
              "        - {result: vector fit, value: sigma.springmann.x0_ut, max: 0.001}"]  # fmt: skip
    return "\n".join(lines) + "\n"


RIG = """
[cage]
axes = { x = "coil_x", y = "coil_y", z = "coil_z" }
reference = "reference"
max_current_a = [2.5, 2.5, 2.5]
max_field_ut = 120.0
max_slew_a_per_s = 10.0
nominal_k_ut_per_a = [[40.0, 0.0, 0.0], [0.0, 40.0, 0.0], [0.0, 0.0, 40.0]]

[devices.dut]
kind = "hmr2300"
protocol = "serial"
path = "/dev/null"
noise_nt = 20.0

[devices.reference]
kind = "ascii-mag"
protocol = "serial"
path = "/dev/null"
noise_nt = 5.0
correction_matrix = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
position_m = [0.0, 0.0, -0.08]
""" + "".join(
    f'\n[devices.{n}]\nkind = "riden-rd60xx"\nprotocol = "modbus-tcp"\nhost = "127.0.0.1"\nport = {9 + i}\n'
    for i, n in enumerate(("coil_x", "coil_y", "coil_z", "load_bus", "load_panel"))
)
"""A rig with a reference certificate and its place: the prediction carries the cage's terms
(certificate and lab field: 12 refits of each calibration)."""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=1000, help="steps in the procedure")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs of each")
    args = parser.parse_args()
    from rig.config import load_rig_config
    from rig.prediction.procedure import predict_procedure
    from rig.procedure.language import parse_procedure
    from rig.procedure.plan import dry_run, rig_timing

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "long.yaml"
        path.write_text(procedure_text(args.steps))
        (Path(tmp) / "rig.toml").write_text(RIG)
        cfg = load_rig_config(Path(tmp) / "rig.toml")
        timing = rig_timing(cfg)
        assert timing is not None
        proc = parse_procedure(path)
        dry, pred = [], []
        for _ in range(args.repeats):
            start = time.perf_counter()
            dry_run(proc, None, None, None, None, {}, timing)
            dry.append(time.perf_counter() - start)
            start = time.perf_counter()
            result = predict_procedure(proc, cfg, timing, None, None)
            pred.append(time.perf_counter() - start)
    samples = [s.samples for s in result.steps]
    d, p = statistics.median(dry), statistics.median(pred)
    a = result.steps[0].parameters[0]
    print(
        f"{len(proc.steps)} steps, {samples} planned samples per calibrate step; scale a:"
        f" statistical {a.statistical:.2g}, combined {a.combined:.2g} ({a.limited_by})"
    )
    print(f"dry run (rig check)      median {d:.3f} s")
    print(f"prediction (--predict)   median {p:.3f} s  ({p / d:.1f} x the dry run)")
    print(f"goal: under 1 s -> {'met' if p < 1.0 else 'NOT met'}")
    return 0 if p < 1.0 else 1


if __name__ == "__main__":
    sys.exit(main())
