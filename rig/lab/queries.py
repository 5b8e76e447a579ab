"""The lab index's questions: runs, every acceptance of a DUT, a parameter's trend with control
limits, and the audit (expired certificates, unsealed runs, runs refused by a sync, which rig
produces the outliers).

Each function returns rows as dicts (JSON-ready: times as ISO strings); units as stored (criteria
in their ``unit``, calibration parameters as in the result file).
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from rig.lab.bounds import PARAMETERS, UNKNOWN, in_range

if TYPE_CHECKING:
    import psycopg

Row = dict[str, Any]
CONTROL_SIGMAS = 3.0
"""Control limits: the lot's mean +- this many (sample) standard deviations."""
MIN_FOR_LIMITS = 3
"""A lot needs this many values before it has control limits."""

RUN_COLUMNS = (
    "r.run_id, r.rig, r.started_at, r.procedure, r.dut_serial, r.lot, r.operator, r.status,"
    " r.verdict"
)


def _rows(conn: psycopg.Connection[Any], sql: str, params: tuple[Any, ...] = ()) -> list[Row]:
    with conn.cursor() as cur:
        cur.execute(sql, params)  # type: ignore[arg-type,unused-ignore]  # constant SQL
        names = [d.name for d in cur.description or ()]
        rows = [dict(zip(names, r, strict=True)) for r in cur.fetchall()]
    conn.rollback()
    for row in rows:
        for k, v in row.items():
            if hasattr(v, "isoformat"):
                row[k] = v.isoformat()
    return rows


def runs(
    conn: psycopg.Connection[Any], *, dut: str | None = None, status: str | None = None,
    limit: int = 50,
) -> list[Row]:  # fmt: skip
    """The newest runs, optionally of one DUT serial and/or one status."""
    where, params = [], []
    if dut is not None:
        where.append("r.dut_serial = %s")
        params.append(dut)
    if status is not None:
        where.append("r.status = %s")
        params.append(status)
    sql = (f"SELECT {RUN_COLUMNS} FROM lab_runs r"
           f"{' WHERE ' + ' AND '.join(where) if where else ''}"
           " ORDER BY r.started_at DESC NULLS LAST, r.id DESC LIMIT %s")  # fmt: skip
    return _rows(conn, sql, (*params, limit))


def dut(conn: psycopg.Connection[Any], serial: str) -> list[Row]:
    """Every run (acceptance) of a DUT serial, oldest first, with failed criteria and reports."""
    return _rows(conn, f"""
        SELECT {RUN_COLUMNS}, r.data_sha256, r.report_files,
               (SELECT count(*) FROM lab_criteria c WHERE c.run = r.id AND c.verdict = 'FAIL')
                   AS failed_criteria,
               (SELECT min(c.margin) FROM lab_criteria c WHERE c.run = r.id) AS min_margin
        FROM lab_runs r WHERE r.dut_serial = %s ORDER BY r.started_at, r.id""", (serial,))  # fmt: skip


POSITIVE_SUFFIXES = ("_rms_nt",)
"""Parameters whose names end so are magnitudes (> 0): their control limits are taken on the
logarithm, so a lower limit is never negative (a residual's lot mean - 3 sd can be)."""


def positive_quantity(param: str) -> bool:
    """Whether ``param`` is a magnitude (:data:`POSITIVE_SUFFIXES`)."""
    return param.endswith(POSITIVE_SUFFIXES)


def series_label(source: Any, lot: Any) -> str:
    """One trend series: a calibration (the step that fitted it) within a lot."""
    return f"{source}, lot {lot}" if lot not in (None, "") else f"{source}, no lot"


@dataclass
class Trend:
    """A parameter over runs: one series per calibration (``source``, the step that fitted it)
    and lot, each with its control limits (mean +- 3 sigma of its values; of their logarithm for
    a magnitude)."""

    param: str
    rows: list[Row]
    limits: dict[str, Row] = field(default_factory=dict)
    """series label -> {source, lot, n, mean, sd, lcl, ucl} (series with fewer than
    MIN_FOR_LIMITS values have none)."""

    @property
    def runs(self) -> int:
        """How many runs the rows come from (a run can hold several calibrations)."""
        return len({row["run_id"] for row in self.rows})

    @property
    def series(self) -> list[str]:
        """The series labels, in order of first appearance."""
        return list(dict.fromkeys(str(row["series"]) for row in self.rows))


def control_limits(values: list[float], positive: bool) -> Row:
    """{n, mean, sd, lcl, ucl} of ``values``: mean +- :data:`CONTROL_SIGMAS` sd, or for a
    ``positive`` quantity (every value > 0) the same on the logarithm, mapped back."""
    mean, sd = statistics.fmean(values), statistics.stdev(values)
    if positive and min(values) > 0:
        logs = [math.log(v) for v in values]
        m, s = statistics.fmean(logs), statistics.stdev(logs)
        lcl, ucl = math.exp(m - CONTROL_SIGMAS * s), math.exp(m + CONTROL_SIGMAS * s)
    else:
        lcl, ucl = mean - CONTROL_SIGMAS * sd, mean + CONTROL_SIGMAS * sd
        lcl = max(lcl, 0.0) if positive else lcl
    return {"n": len(values), "mean": mean, "sd": sd, "lcl": lcl, "ucl": ucl}


def trend(conn: psycopg.Connection[Any], param: str, *, lot: str | None = None) -> Trend:
    """``param`` (a calibration result name, e.g. ``x0_ut``) over runs in time order, one series
    per calibration and lot (``series``); each row flagged ``outlier`` when outside its series'
    control limits or outside the parameter's physical range (``in_range`` false: such a value,
    stored before syncs refused it, is left out of the limits, :mod:`rig.lab.bounds`)."""
    rows = _rows(conn, """
        SELECT r.run_id, r.rig, r.lot, r.dut_serial, r.started_at, s.source, s.value, s.sigma
        FROM lab_results s JOIN lab_runs r ON r.id = s.run
        WHERE s.name = %s AND (%s::text IS NULL OR r.lot = %s)
        ORDER BY r.started_at, r.id, s.source""", (param, lot, lot))  # fmt: skip
    by_series: dict[str, list[float]] = {}
    for row in rows:
        row["series"] = series_label(row["source"], row["lot"])
        # a value beyond the physical range (stored by an older sync) is no part of the limits
        row["in_range"] = in_range(param, float(row["value"]))
        values = by_series.setdefault(row["series"], [])
        if row["in_range"]:
            values.append(float(row["value"]))
    limits = {}
    positive = positive_quantity(param)
    for row in rows:
        name = row["series"]
        if name not in limits and len(by_series[name]) >= MIN_FOR_LIMITS:
            limits[name] = {"source": row["source"], "lot": row["lot"],
                            **control_limits(by_series[name], positive)}  # fmt: skip
    for row in rows:
        lim = limits.get(row["series"])
        row["outlier"] = not row["in_range"] or (
            bool(lim) and not lim["lcl"] <= row["value"] <= lim["ucl"]  # type: ignore[index]
        )
    return Trend(param, rows, limits)


def refusals(conn: psycopg.Connection[Any]) -> list[Row]:
    """Runs a sync refused (table ``lab_refusals``: changed since they were sealed, or not
    storable), the most recently refused first: one row per run, seal and kind of refusal."""
    return _rows(conn, """
        SELECT run_id, rig, host, kind, reason, sealed_sha256, first_at, last_at, attempts
        FROM lab_refusals ORDER BY last_at DESC, run_id""")  # fmt: skip


def audit(conn: psycopg.Connection[Any]) -> dict[str, list[Row]]:
    """Runs that used an instrument whose certificate had expired; runs without a seal (no data
    hash); runs a sync refused (changed since they were sealed, not sealed, a value out of range,
    or not storable); and per rig: runs, failed criteria and calibration values outside their
    series' control limits (mean +- 3 sigma of the parameter over the same calibration in the
    same lot) or outside the parameter's physical range (:mod:`rig.lab.bounds`; such a value,
    stored by an older sync, is counted an outlier and left out of the limits, so it can neither
    move them nor overflow them)."""
    expired = _rows(conn, """
        SELECT r.run_id, r.rig, r.started_at, r.dut_serial, i.name AS instrument, i.serial,
               i.certificate_expires
        FROM lab_instruments i JOIN lab_runs r ON r.id = i.run
        WHERE i.expired ORDER BY r.started_at, r.id, i.name""")  # fmt: skip
    unsealed = _rows(conn, """
        SELECT r.run_id, r.rig, r.started_at, r.status FROM lab_runs r
        WHERE r.data_sha256 IS NULL ORDER BY r.started_at, r.id""")  # fmt: skip
    refused = refusals(conn)
    ranges = ", ".join(["(%s, %s::float8, %s::float8)"] * len(PARAMETERS))
    per_rig = _rows(conn, f"""
        WITH ranges (name, lo, hi) AS (VALUES {ranges}),
        vals AS MATERIALIZED (
            SELECT r.rig, coalesce(r.lot, '') AS lot, s.source, s.name, s.value,
                   coalesce(s.value BETWEEN coalesce(g.lo, -{UNKNOWN}::float8)
                                        AND coalesce(g.hi, {UNKNOWN}::float8), false) AS in_range
            FROM lab_results s JOIN lab_runs r ON r.id = s.run LEFT JOIN ranges g USING (name)),
        lots AS (
            SELECT name, source, lot, avg(value) AS m, stddev_samp(value) AS sd FROM vals
            WHERE in_range GROUP BY name, source, lot HAVING count(*) >= {MIN_FOR_LIMITS}),
        outliers AS (
            SELECT v.rig, count(*) FILTER (WHERE l.m IS NOT NULL OR NOT v.in_range) AS n,
                   count(*) FILTER (WHERE NOT v.in_range OR (l.m IS NOT NULL
                                    AND abs(v.value - l.m) > {CONTROL_SIGMAS} * l.sd)) AS outliers
            FROM vals v LEFT JOIN lots l USING (name, source, lot) GROUP BY v.rig),
        crit AS (
            SELECT r.rig, count(*) AS n, count(*) FILTER (WHERE c.verdict = 'FAIL') AS failed
            FROM lab_criteria c JOIN lab_runs r ON r.id = c.run GROUP BY r.rig),
        rigs AS (
            SELECT rig, count(*) AS runs, count(*) FILTER (WHERE verdict = 'FAIL') AS failed_runs
            FROM lab_runs GROUP BY rig)
        SELECT g.rig, g.runs, g.failed_runs, coalesce(c.n, 0) AS criteria,
               coalesce(c.failed, 0) AS failed_criteria,
               coalesce(c.failed::float / nullif(c.n, 0), 0) AS failed_fraction,
               coalesce(o.n, 0) AS values, coalesce(o.outliers, 0) AS outliers,
               coalesce(o.outliers::float / nullif(o.n, 0), 0) AS outlier_fraction
        FROM rigs g LEFT JOIN crit c USING (rig) LEFT JOIN outliers o USING (rig)
        ORDER BY outlier_fraction DESC, failed_fraction DESC, g.rig""",
        tuple(x for name, (lo, hi) in PARAMETERS.items() for x in (name, lo, hi)))  # fmt: skip
    return {"expired_certificates": expired, "unsealed": unsealed, "refused": refused,
            "rigs": per_rig}  # fmt: skip


def table(rows: list[Row], columns: list[str] | None = None) -> str:
    """Rows as an aligned text table (floats to 4 significant digits, None as '-')."""
    if not rows:
        return "(none)"
    cols = columns or list(rows[0])

    def cell(v: Any) -> str:
        if v is None:
            return "-"
        if isinstance(v, float):
            return f"{v:.4g}" if math.isfinite(v) else str(v)
        if isinstance(v, list):
            return ",".join(map(str, v)) or "-"
        return str(v)

    cells = [[cell(r.get(c)) for c in cols] for r in rows]
    widths = [max(len(c), *(len(r[i]) for r in cells)) for i, c in enumerate(cols)]
    lines = ["  ".join(c.upper().ljust(w) for c, w in zip(cols, widths, strict=True)).rstrip()]
    lines += ["  ".join(v.ljust(w) for v, w in zip(r, widths, strict=True)).rstrip() for r in cells]
    return "\n".join(lines)
