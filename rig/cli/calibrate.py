"""``rig calibrate``: fit the measurement model to a CSV file or a stored run."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rig.calibration.estimators import DEFAULT_METHOD, method_names, spoken
from rig.cli.common import EXIT_OK, Parser, Subparsers, check_outputs, columns, write_text
from rig.errors import UserInputError
from rig.io.field_units import UNIT_HELP

if TYPE_CHECKING:
    from rig.calibration.budget import CageTerms  # numpy: loaded only when a command runs


def add_parser(sub: Subparsers, parents: list[Parser]) -> None:
    cal = sub.add_parser(
        "calibrate",
        parents=parents,
        help="fit scale, offset, misalignment and current-to-bias to a CSV file",
        description=(
            "Fit m = T h + o + sum_j k_j u_j to recorded data. --field gives a vector (cage)"
            " calibration, --field-magnitude an attitude-independent (scalar) one. Field columns"
            " are read in --unit (and --field-unit) and converted to uT; results are in uT and nT."
        ),
    )
    cal.add_argument(
        "data",
        type=Path,
        metavar="DATA.csv|RUN",
        help="CSV file with a header row, a run folder, or a run id under --runs-dir",
    )
    cal.add_argument(
        "--runs-dir",
        type=Path,
        default=Path("runs"),
        metavar="DIR",
        help="where to look for a run id (default: runs)",
    )
    cal.add_argument(
        "--measured", type=columns, metavar="COLX,COLY,COLZ",
        help="raw DUT reading columns",
    )  # fmt: skip
    ref = cal.add_mutually_exclusive_group()
    ref.add_argument(
        "--field", type=columns, metavar="COLX,COLY,COLZ",
        help="reference field vector columns (vector calibration)",
    )  # fmt: skip
    ref.add_argument(
        "--field-magnitude",
        metavar="COL|VALUE",
        help="reference field magnitude (scalar calibration): a column, or one number for a"
        " constant field (e.g. 0.47 with --unit G); in --field-unit",
    )
    ref.add_argument(
        "--igrf", metavar="LAT,LON,ALT_KM,DATE",
        help="constant reference magnitude from IGRF at this place (degrees, degrees east, km"
        " above the ellipsoid) and date (YYYY-MM-DD): a sensor turned in the Earth's field",
    )  # fmt: skip
    cal.add_argument(
        "--unit",
        default="uT",
        metavar="UNIT",
        help=f"unit of the --measured columns: {UNIT_HELP} (default uT); results are in uT"
        " and nT whatever the file's unit",
    )
    cal.add_argument(
        "--field-unit",
        metavar="UNIT",
        help="unit of the reference (--field, --field-magnitude): default the same as --unit,"
        " or uT when --unit is a counts factor",
    )
    cal.add_argument(
        "--allow-implausible-field", action="store_true",
        help="accept a reference or readings far from any calibration field in the units given",
    )  # fmt: skip
    cal.add_argument(
        "--columns", type=columns, metavar="NAME1,NAME2,...",
        help="the file has no header row: these are its columns, in order",
    )  # fmt: skip
    cal.add_argument(
        "--drop-invalid",
        action="store_true",
        help="leave out rows with an empty, non-numeric, NaN or infinite cell in a column used"
        " (their count is printed) instead of refusing the file",
    )
    cal.add_argument(
        "--median",
        type=_odd_window,
        metavar="N",
        help="moving-median prefilter of the --measured columns over N samples (odd, 3-101),"
        " in file order (centred: no delay), against isolated spikes; rows must be in time order",
    )
    cal.add_argument(
        "--telemetry", type=columns, default=[], metavar="COL1,COL2,...",
        help="telemetry channels (currents) whose bias to fit",
    )  # fmt: skip
    cal.add_argument(
        "--time", metavar="COL",
        help="sample time column in seconds (any origin, increasing): needed by --delay",
    )  # fmt: skip
    cal.add_argument(
        "--delay", type=columns, default=[], metavar="COL1,...",
        help="--telemetry channels whose delay to estimate (s; the current reaches the reading"
        " that much after the telemetry shows it), with its 1-sigma and Cramer-Rao bound",
    )  # fmt: skip
    cal.add_argument(
        "--max-delay-s", type=float, default=2.0, metavar="S",
        help="search --delay within +-S seconds (default 2)",
    )  # fmt: skip
    cal.add_argument(
        "--temperature", metavar="COL",
        help="DUT temperature column (K or degrees C), or for a run the thermometer it recorded"
        " (e.g. dut_temp): fits the offset (uT/K, per axis) and the scale (ppm/K) per kelvin,"
        " with 1-sigma and Cramer-Rao bound",
    )  # fmt: skip
    cal.add_argument(
        "--temperature-ref", type=float, metavar="T",
        help="temperature the other parameters refer to (default: the mean of --temperature)",
    )  # fmt: skip
    cal.add_argument(
        "--method",
        choices=method_names(),
        help=f"estimator (default: {DEFAULT_METHOD['vector']} with --field,"
        f" {DEFAULT_METHOD['scalar']} with --field-magnitude);"
        f" {spoken(method_names(kind='sequential'), 'and')} are the sequential (real-time)"
        " filters, run over the rows in file order",
    )
    cal.add_argument(
        "--filter-variant",
        choices=("energy", "paper", "paper-augmented"),
        default="energy",
        help="ekf/ukf form: energy (default, converges from a zero start), paper (Crassidis et al."
        " as published), paper-augmented (12-state UKF)",
    )
    cal.add_argument(
        "--backend",
        choices=("numpy", "filterpy"),
        default="numpy",
        help="filter implementation (filterpy runs the paper variants)",
    )
    cal.add_argument(
        "--history", type=Path, metavar="HISTORY.csv",
        help="write the filter's estimate and 1-sigma per parameter as it converges (CSV)",
    )  # fmt: skip
    cal.add_argument(
        "--noise-nt", type=float, metavar="SIGMA",
        help="raw noise per axis, 1-sigma in nT: the chi-square test and Cramer-Rao bound use it",
    )  # fmt: skip
    cal.add_argument(
        "--robust",
        choices=("huber", "bisquare"),
        help=f"reweight against outliers ({', '.join(method_names(robust=True))})",
    )
    cal.add_argument("--out", type=Path, metavar="RESULT.json", help="write the result file")
    cal.add_argument(
        "--c-header", type=Path, metavar="FILE.h", help="write a C header for flight software"
    )
    cal.add_argument(
        "--ardupilot",
        type=Path,
        metavar="FILE.parm",
        help="write ArduPilot compass parameters (COMPASS_OFS/DIA/ODI, mGauss; Mission Planner or"
        " MAVProxy parameter file)",
    )
    cal.add_argument(
        "--ardupilot-compass",
        type=int,
        default=1,
        metavar="N",
        help="ArduPilot compass 1, 2 or 3 for --ardupilot (default 1: COMPASS_OFS_X, 2:"
        " COMPASS_OFS2_X, ...)",
    )
    cal.add_argument(
        "--px4",
        type=Path,
        metavar="FILE.params",
        help="write PX4 magnetometer parameters (CAL_MAGn_xOFF/xSCALE/xODIAG, gauss;"
        " QGroundControl parameter file)",
    )
    cal.add_argument(
        "--px4-instance",
        type=int,
        default=0,
        metavar="N",
        help="PX4 magnetometer instance 0 to 3 for --px4 (default 0: CAL_MAG0_*)",
    )
    cal.add_argument(
        "--autopilot-current",
        metavar="CHANNEL",
        help="a --telemetry channel that is the battery current in A: its current-to-bias goes"
        " to COMPASS_MOT (--ardupilot) and CAL_MAGn_xCOMP (--px4); other channels are left out",
    )
    cal.set_defaults(func=_cmd_calibrate)


def _check_csv_args(args: argparse.Namespace) -> None:
    """UserInputError (one line, the fix) unless the options describe a CSV calibration."""
    if args.measured is None:
        raise UserInputError("--measured COLX,COLY,COLZ is required for a CSV file")
    if args.field is None and args.field_magnitude is None and args.igrf is None:
        raise UserInputError(
            "give --field COLX,COLY,COLZ (vector), --field-magnitude COL|VALUE or --igrf"
            " LAT,LON,ALT_KM,DATE (scalar)"
        )
    if len(args.measured) != 3:
        raise UserInputError(f"--measured needs three columns X,Y,Z, got {len(args.measured)}")
    if args.field is not None and len(args.field) != 3:
        raise UserInputError(f"--field needs three columns X,Y,Z, got {len(args.field)}")
    if len(set(args.telemetry)) != len(args.telemetry):
        raise UserInputError("--telemetry names a column twice: list each channel once")


def _read_columns(args: argparse.Namespace, wanted: list[str]) -> Any:
    """The ``wanted`` columns of the CSV file (rows with a bad value left out and counted with
    ``--drop-invalid``), as one float array in that order."""
    import numpy as np

    from rig.io.csv_table import read_table, read_valid_rows

    if args.drop_invalid:
        valid, dropped = read_valid_rows(args.data, wanted, names=args.columns)
        if dropped and not args.quiet:
            lines = ", ".join(str(n) for n in dropped[:5]) + (", ..." if len(dropped) > 5 else "")
            n_rows = len(valid[wanted[0]]) + len(dropped)
            print(f"--drop-invalid: left out {len(dropped)} of {n_rows} rows (lines {lines})",
                  file=sys.stderr)  # fmt: skip
        return np.column_stack([valid[c] for c in wanted])
    return read_table(args.data, wanted, names=args.columns)


def _csv_samples(args: argparse.Namespace, table: Any, wanted: list[str], constant: float | None,
                 factors: tuple[float, float]) -> Any:  # fmt: skip
    """The CSV columns as calibration samples (uT; ``factors``: the measured and field columns'
    uT per unit; ``constant``: a field magnitude in the field unit, for every row)."""
    import numpy as np

    from rig.calibration import Samples

    measured_ut_per, field_ut_per = factors

    def block(names: list[str], factor: float = 1.0) -> Any:
        """The named columns: a view of the table when adjacent (no copy of a large file)."""
        idx = [wanted.index(c) for c in names]
        view = (table[:, idx[0] : idx[0] + len(idx)] if idx == list(range(idx[0], idx[0] + len(idx)))
                else table[:, idx])  # fmt: skip
        return view if factor == 1.0 else factor * view

    measured = block(args.measured, measured_ut_per)
    if args.median is not None:
        from rig.io.prefilter import moving_median

        measured = moving_median(measured, args.median)
    telemetry = block(args.telemetry) if args.telemetry else None
    if args.field is not None:
        samples = Samples.build(
            measured,
            field_ut=block(args.field, field_ut_per),
            telemetry=telemetry,
            channels=tuple(args.telemetry),
        )
    else:
        magnitude_ut = (
            np.full(len(measured), field_ut_per * constant)
            if constant is not None
            else block([args.field_magnitude], field_ut_per)[:, 0]
        )
        samples = Samples.build(
            measured,
            field_magnitude_ut=magnitude_ut,
            telemetry=telemetry,
            channels=tuple(args.telemetry),
        )
    return samples


def _cmd_calibrate(args: argparse.Namespace) -> int:
    import os

    # One BLAS thread unless the user says otherwise (before numpy loads): the fits' products are
    # tall and thin (blocks of 32k rows x <= 70 columns), a second thread gains nothing and, on a
    # busy machine, spinning threads took the 100k x 69 fit from 1.1 s to 2.7-3.7 s (ADR 0017).
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    # every file the user named, before the fit: a planted link refuses the command, writes nothing
    check_outputs([args.out, args.c_header, args.ardupilot, args.px4, args.history])
    if args.data.is_dir():
        return _calibrate_run(args)
    if not args.data.exists():
        run_folder = args.runs_dir / args.data
        if (run_folder / "run.sqlite").exists():
            args.data = run_folder
            return _calibrate_run(args)
        if args.data.suffix.lower() != ".csv":
            raise UserInputError(
                f"no CSV file or run '{args.data}' (looked at {args.data} and {run_folder}):"
                " give a CSV file, a run folder, or a run id listed by 'rig runs' (--runs-dir DIR)"
            )
    _check_csv_args(args)
    measured_ut_per, field_ut_per = _unit_factors(args)
    constant = _constant_magnitude(args)
    if args.igrf is not None:
        from rig.geomag import igrf_magnitude_ut, parse_igrf_site

        lat, lon, alt, date = parse_igrf_site(args.igrf)
        constant = igrf_magnitude_ut(lat, lon, alt, date) / field_ut_per  # in the field unit
        if not args.quiet:
            print(f"--igrf: |B| = {constant * field_ut_per:.3f} uT (IGRF at {lat:g}, {lon:g},"
                  f" {alt:g} km on {date:%Y-%m-%d})", file=sys.stderr)  # fmt: skip
    magnitude = [] if args.field is not None or constant is not None else [args.field_magnitude]
    if args.delay and args.time is None:
        raise UserInputError("--delay needs the sample times: add --time COL (seconds)")
    if args.temperature_ref is not None and args.temperature is None:
        raise UserInputError("--temperature-ref needs --temperature COL")
    timing = [args.time] if args.time is not None else []
    timing += [args.temperature] if args.temperature is not None else []
    wanted = list(args.measured) + (args.field or magnitude) + list(args.telemetry) + timing
    wanted = list(dict.fromkeys(wanted))
    import numpy as np

    table = _read_columns(args, wanted)
    cols = {c: table[:, j] for j, c in enumerate(wanted)}
    samples = _csv_samples(args, table, wanted, constant, (measured_ut_per, field_ut_per))
    from rig.cli.field_sanity import check_plausible_fields

    check_plausible_fields(samples, args)
    times_s = np.asarray(cols[args.time], float) if args.time is not None else None
    temperature = np.asarray(cols[args.temperature], float) if args.temperature else None
    return _fit_and_emit(samples, args, times_s, temperature)


def _odd_window(text: str) -> int:
    """``--median N``: an odd window of 3 to 101 samples."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number of samples") from None
    if n < 3 or n > 101 or n % 2 == 0:
        raise argparse.ArgumentTypeError(f"{n}: give an odd window of 3 to 101 samples")
    return n


def _unit_factors(args: argparse.Namespace) -> tuple[float, float]:
    """uT per file unit of the measured columns and of the reference."""
    from rig.io.field_units import is_counts, ut_per

    field_unit = args.field_unit or ("uT" if is_counts(args.unit) else args.unit)
    try:
        return ut_per(args.unit), ut_per(field_unit)
    except ValueError as exc:
        raise UserInputError(f"--unit/--field-unit: {exc}") from None


def _constant_magnitude(args: argparse.Namespace) -> float | None:
    """--field-magnitude as a number (a constant field), or None when it names a column."""
    import math

    if args.field_magnitude is None or args.field_magnitude in (args.columns or []):
        return None
    try:
        value = float(args.field_magnitude)
    except ValueError:
        return None
    if not (math.isfinite(value) and value > 0):
        raise UserInputError(
            f"--field-magnitude {args.field_magnitude}: a constant field magnitude must be a"
            " positive number"
        )
    return value


def _fit_and_emit(
    samples: Any, args: argparse.Namespace, times_s: Any = None, temperature: Any = None,
    series: Any = None, delay_resolution_s: dict[str, float] | None = None,
    clock_offset: Any = None, cage: CageTerms | None = None,
) -> int:  # fmt: skip
    """Fit, write the result file, C header and autopilot parameters if asked, print the table.
    ``delay_resolution_s``: channels whose delay is known only to within an interval (s), which
    their sigma then includes; ``clock_offset``: the reference field series and bound (s) of the
    offset between the DUT's and the reference's dates, fitted with the delays."""
    from rig.calibration import calibrate
    from rig.report.tables import calibration_table

    filter_methods = method_names(kind="sequential")
    if args.history is not None and args.method not in filter_methods:
        raise UserInputError(f"--history needs a filter: add --method {spoken(filter_methods)}")
    opts = None
    if args.method in filter_methods:
        from rig.calibration.sequential.realtime import FilterOptions

        opts = FilterOptions(args.method, args.filter_variant, args.backend)

    def fit(s: Any) -> Any:
        return calibrate(s, args.method, noise_nt=args.noise_nt, robust=args.robust,
                         filter_options=opts, times_s=times_s, delays=tuple(args.delay),
                         max_delay_s=args.max_delay_s, temperature=temperature,
                         temperature_ref=args.temperature_ref, telemetry_series=series,
                         clock_offset=clock_offset)  # fmt: skip

    result = fit(samples)
    if delay_resolution_s and result.profiled is not None:
        from dataclasses import replace

        from rig.calibration.profiled import with_resolution

        widened = with_resolution(result.profiled, "delay_s", delay_resolution_s)
        result = replace(result, profiled=widened)
    autopilot = _autopilot_files(result, args)  # before any file: a refusal writes nothing
    if args.history is not None and result.history is not None:
        write_text(args.history, _history_csv(result))
    content = result.to_dict()
    if cage is not None and args.method not in filter_methods:
        content |= _budget(result, samples, fit, cage)
    if args.out is not None:
        write_text(args.out, json.dumps(content, indent=2) + "\n")
    if args.c_header is not None:
        from rig.calibration.export_c import c_header

        write_text(
            args.c_header, c_header(result, prefix=args.c_header.stem, source=str(args.data))
        )
    for path, text in autopilot:
        write_text(path, text)
    if not args.quiet:
        print(calibration_table(result, source=str(args.data), verbose=args.verbose))
        if "combined_sigma" in content:
            print(combined_line(content))
        for path in (args.out, args.c_header, args.ardupilot, args.px4, args.history):
            if path is not None:
                print(f"wrote {path}")
    return EXIT_OK


def _budget(result: Any, samples: Any, fit: Any, cage: CageTerms) -> dict[str, Any]:
    """The result's ``combined_sigma`` and ``uncertainty_budget``: ``fit`` (the same options)
    refitted once per cage term (ADR 0028)."""
    from rig.analysis import budget_block
    from rig.calibration.budget import propagate

    budget = propagate(samples, lambda s: fit(s).reported(), result.reported(),
                       result.reported_sigma(), cage.terms, cage.left_out)  # fmt: skip
    return budget_block(result, budget)


def combined_line(content: dict[str, Any]) -> str:
    """The combined 1-sigma of the Springmann values with the cage's terms, and what the budget
    left out, for the terminal (the --out file has every term)."""
    combined = content["combined_sigma"]["springmann"]
    budget = content["uncertainty_budget"]
    line = ("combined 1-sigma with the cage's terms ("
            + ", ".join(budget["groups"]) + "): "
            + ", ".join(f"{k} {v:.2g}" for k, v in combined.items()))  # fmt: skip
    if budget["left_out"]:
        line += "; not in it: " + "; ".join(budget["left_out"])
    return line


def _autopilot_files(result: Any, args: argparse.Namespace) -> list[tuple[Path, str]]:
    """The --ardupilot and --px4 files' text; an export the autopilot cannot take is an input
    error."""
    from rig.calibration.export_autopilot import ardupilot_params, px4_params

    if args.autopilot_current is not None and args.ardupilot is None and args.px4 is None:
        raise UserInputError("--autopilot-current needs --ardupilot FILE.parm or --px4 FILE.params")
    out: list[tuple[Path, str]] = []
    exports = (
        (args.ardupilot, ardupilot_params, args.ardupilot_compass),
        (args.px4, px4_params, args.px4_instance),
    )
    try:
        for path, export, slot in exports:
            if path is not None:
                text = export(
                    result, slot, current_channel=args.autopilot_current, source=str(args.data)
                )
                out.append((path, text))
    except ValueError as exc:
        raise UserInputError(str(exc)) from None
    return out


def _delay_inputs(reader: Any, channels: list[str], t_s: Any) -> tuple[Any, ...]:
    """What a delay fit of a stored run needs: each channel's commanded series, the interval it
    was commanded in step with the DUT at (or None), the resolution its sigma must include (s),
    and the reference field series with the bound of the DUT-reference date offset."""
    import numpy as np

    from rig.analysis import (
        CLOCK_OFFSET_MIN_BOUND_S,
        load_commands,
        phase_locked_interval_s,
        reference_field_series,
        telemetry_series,
        write_window_s,
    )

    width_s = 2.0 * float(np.median(np.diff(t_s))) if t_s.size > 1 else 0.1
    series = {ch: telemetry_series(reader, ch, width_s) for ch in channels}
    commands = {ch: load_commands(reader, ch) for ch in channels}
    locked = {ch: phase_locked_interval_s(commands[ch], t_s) for ch in channels}
    # when a command took effect is known only to within its write (issued .. answered): wide
    # on a busy computer; that width enters the delay's sigma too (ADR 0020)
    writes = {ch: write_window_s(c, t_s, width_s) for ch, c in commands.items()}
    resolution = {ch: float(np.hypot(locked[ch] or 0.0, writes[ch])) for ch in channels}
    # the DUT's and the reference's dates may differ by their streams' latencies: with delays,
    # that offset is fitted too (within two DUT periods, at least 50 ms; issue 30)
    clock_offset = (reference_field_series(reader), max(width_s, CLOCK_OFFSET_MIN_BOUND_S))
    return series, locked, resolution, clock_offset


def _history_csv(result: Any) -> str:
    """The filter history as CSV: sample number, every parameter, then every 1-sigma."""
    import io

    import numpy as np

    from rig.calibration.sequential.realtime import history_table

    header, body = history_table(result.history, result.names)
    buf = io.StringIO()
    buf.write(",".join(header) + "\n")
    np.savetxt(buf, body, delimiter=",", fmt="%.9g")
    return buf.getvalue()


def _calibrate_run(args: argparse.Namespace) -> int:
    """Re-fit the DUT from a stored run (its procedure's magnetometers and loads by default);
    ``--method ml`` (or another scalar method) fits attitude-independently from the same data."""
    from rig.analysis import (
        MAX_TEMPERATURE_GAP_S,
        late_timeline_fault,
        recorded_thermometer,
        run_temperature,
        stored_run_data,
        unresolved_note,
    )
    from rig.calibration.budget import corrected
    from rig.steps import field_kinds
    from rig.store import RunReader
    from rig.timing import misdated_note

    if args.temperature_ref is not None and args.temperature is None:
        raise UserInputError("--temperature-ref needs --temperature THERMOMETER")
    reader = RunReader(args.data)
    try:
        if args.temperature:
            recorded_thermometer(reader, args.temperature)
        telemetry = list(args.telemetry) if args.telemetry else list(reader.meta().get("loads", []))
        samples, t_s, unresolved, misdated, late = stored_run_data(
            reader, telemetry, field_kinds=field_kinds()
        )
        fault = late_timeline_fault(late, samples.n + unresolved)
        if fault is not None:
            raise UserInputError(fault)
        delays = _delay_inputs(reader, args.delay, t_s)
        temperature = None
        if args.temperature:
            samples, temperature, left_out = run_temperature(reader, args.temperature, samples, t_s)
            if left_out and not args.quiet:
                print(f"note: left out {left_out} of {left_out + samples.n} samples with no"
                      f" {args.temperature} reading within {MAX_TEMPERATURE_GAP_S:g} s",
                      file=sys.stderr)  # fmt: skip
        cage = _run_cage_terms(reader, args.data)
        samples = corrected(samples, cage.correction)  # to the DUT's place, as the run's fit
    finally:
        reader.close()
    series, locked, resolution, clock_offset = delays
    for ch, interval in locked.items():
        if interval is not None and not args.quiet:
            print(f"note: the DUT sampled in step with the {1 / interval:.3g} Hz commands of {ch}:"
                  f" its delay is known only to within {1000 * interval:.0f} ms; its sigma"
                  " includes that (width / sqrt 12)", file=sys.stderr)  # fmt: skip
    if unresolved and not args.quiet:
        print(f"note: {unresolved_note(unresolved, samples.n + unresolved)}", file=sys.stderr)
    if misdated and not args.quiet:
        judged = samples.n + unresolved + sum(m.samples for m in misdated)
        print(f"note: {misdated_note(misdated, judged)}", file=sys.stderr)
    return _fit_and_emit(samples, args, times_s=t_s if args.delay else None, series=series,
                         temperature=temperature, delay_resolution_s=resolution,
                         clock_offset=clock_offset, cage=cage)  # fmt: skip


def _run_cage_terms(reader: Any, folder: Path) -> CageTerms:
    """The cage's terms the run recorded (its reference certificate, cage record and rig
    configuration's copy): a refit carries the same uncertainty budget as the run's own fit."""
    from rig.cage_budget import run_cage_terms

    copy = Path(folder) / "rig.toml"
    return run_cage_terms(
        reader.meta(), copy.read_text(encoding="utf-8") if copy.exists() else None
    )
