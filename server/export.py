"""A chart's data as CSV (pure): what the Export row under every chart sends to the browser
that asked.

One column per series of the chart (x first), in the chart's order; the header is each
series' label with its unit (the label of the axis its scale is drawn on); one row per x
value; NaN (no point there) is an empty cell; numbers are written as Python's shortest
round-trip form, so the file holds exactly the chart's float64 values. The live charts'
data is what they draw (min/max decimated); full-rate records come from `dobtune record`.
"""

from __future__ import annotations

import csv
import io
import math
import re
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from server.charts import MARK_SCALE, ChartSpec

__all__ = ["chart_csv", "column_header", "export_filename", "exported_columns"]

#: The unit written for the crossover-mark series (a fixed 0..1 scale without an axis).
MARK_UNIT = "mark 0/1"


def export_filename(spec: ChartSpec, ext: str) -> str:
    """`dobtune-<title slug>.<ext>` (the whole title, lower case, non-alphanumerics as '-': a
    name cut at 48 characters lost what told two exports apart): the same stem for the chart's
    CSV (made here) and its PNG (made in the browser by web_assets/dashboard.js, same rule)."""
    slug = re.sub(r"[^a-z0-9]+", "-", spec.title.lower()).strip("-")
    return f"dobtune-{slug or 'chart'}.{ext}"


def _unit(spec: ChartSpec, scale: str) -> str:
    """The label of the axis that draws `scale` ("" if none)."""
    if scale == MARK_SCALE:
        return MARK_UNIT
    for axis in spec.axes:
        if axis.get("scale", "y") == scale and axis.get("label"):
            return str(axis["label"])
    return ""


def column_header(spec: ChartSpec) -> list[str]:
    """`label (unit)` per series; the unit is left out when the label already ends with it or
    is it, or when the series' axis has no label (a dimensionless coherence, say)."""
    out = []
    for i, s in enumerate(spec.series):
        label = str(s.get("label", f"series {i}"))
        unit = _unit(spec, "x" if i == 0 else str(s.get("scale", "y")))
        if unit and unit != label and not label.endswith(f"({unit})"):
            label = f"{label} ({unit})"
        out.append(label)
    return out


def exported_columns(spec: ChartSpec, data: Sequence[npt.ArrayLike],
                     ) -> list[npt.NDArray[np.float64]]:
    """The chart's columns as float64, checked against the spec (the charts hold no stand-in
    values: NaN where a series has no point)."""
    if len(data) != len(spec.series):
        raise ValueError(f"data: {len(data)} columns for the {len(spec.series)} series of "
                         f"chart {spec.key!r}")
    cols = [np.asarray(c, dtype=np.float64) for c in data]
    n = cols[0].shape
    for s, c in zip(spec.series, cols, strict=True):
        if c.ndim != 1 or c.shape != n:
            raise ValueError(f"data: series {s.get('label')!r} of chart {spec.key!r} has "
                             f"shape {c.shape}, the x column {n}")
    return cols


def _cell(v: float) -> str:
    return "" if math.isnan(v) else repr(v)


def chart_csv(spec: ChartSpec, data: Sequence[npt.ArrayLike]) -> str:
    """The chart's data as CSV text (header, then one row per x value; see the module)."""
    cols = exported_columns(spec, data)
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(column_header(spec))
    for row in zip(*(c.tolist() for c in cols), strict=True):
        w.writerow([_cell(v) for v in row])
    return buf.getvalue()
