"""The trend plot: a parameter over runs with each lot's control limits, as a PNG."""

from __future__ import annotations

import io
from pathlib import Path

from rig.io.output_files import write_output
from rig.lab.queries import Trend


def trend_png(trend: Trend, path: Path) -> None:
    """Values (with 1-sigma bars) in run order, one colour per series (calibration and lot), its
    mean and control limits as lines; outliers circled; values beyond the parameter's physical
    range (``in_range`` false) are not drawn, only counted in the title. matplotlib is imported
    here only."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 4.5))
    try:
        for series in trend.series:
            idx = [i for i, r in enumerate(trend.rows)
                   if r["series"] == series and r.get("in_range", True)]  # fmt: skip
            vals = [float(trend.rows[i]["value"]) for i in idx]
            sig = [float(trend.rows[i]["sigma"] or 0.0) for i in idx]
            line = ax.errorbar(idx, vals, yerr=sig, fmt=".", ms=4, label=series)
            lim = trend.limits.get(series)
            if lim:
                color = line[0].get_color()
                lo, hi = min(idx), max(idx)
                ax.hlines([lim["mean"]], lo, hi, colors=color, linestyles="-", lw=0.8)
                ax.hlines([lim["lcl"], lim["ucl"]], lo, hi, colors=color, linestyles="--", lw=0.8)
        out = [i for i, r in enumerate(trend.rows) if r["outlier"] and r.get("in_range", True)]
        ax.plot(out, [trend.rows[i]["value"] for i in out], "o", mfc="none", mec="red", ms=9,
                label="outside mean +- 3 sigma")  # fmt: skip
        ax.set_xlabel("calibration (time order)")
        ax.set_ylabel(trend.param)
        beyond = sum(1 for r in trend.rows if not r.get("in_range", True))
        ax.set_title(
            f"{trend.param}: {trend.runs} runs, {len(trend.rows)} calibrations,"
            " control limits per calibration and lot"
            + (f"; {beyond} beyond the physical range not drawn" if beyond else "")
        )
        ax.legend(fontsize=7, ncol=2)
        fig.tight_layout()
        path.parent.mkdir(parents=True, exist_ok=True)
        png = io.BytesIO()
        fig.savefig(png, format="png", dpi=110)
        write_output(path, png.getvalue())  # atomically, never through a link (issue 51)
    finally:
        plt.close(fig)
