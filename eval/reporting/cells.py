"""Table RQ1's cells: which metrics head it, how each is printed, and the reference policies'
columns (eval/reporting/report.py builds the table, eval/reporting/page.py the page's first
screen from them)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

HEADLINE = ("DS", "RC", "success")
"""Table RQ1's first rows: the driving score, route completion and success rate."""
TABLE_METRICS = (*HEADLINE, "IP", "CV_events", "CO_events", "CP_events",
                 "CV", "CO", "CP", "OS", "RL", "TTFC", "SPEED", "DISTANCE", "return", "goal")
"""Table RQ1's rows: the driving score's (:data:`HEADLINE`, then the infraction penalty and the
collision events per AC-episode of each kind), then the paper's metrics, the return and the
goal rate."""
UNITS = {"TTFC": "s", "SPEED": "km/h", "DISTANCE": "m"}


DIGITS = {"TTFC": 2, "SPEED": 2, "DISTANCE": 2, "return": 1, "goal": 2, "success": 2,
          "CV_events": 2, "CO_events": 2, "CP_events": 2}
"""Decimals per metric (3 for DS, RC, IP and the step fractions CV..RL)."""
ROW_NAMES = {"goal": "goal rate", "success": "success rate", "CV_events": "CV events",
             "CO_events": "CO events", "CP_events": "CP events"}
"""How a metric's row is headed where its key is not its name."""


def _digits(metric: str) -> int:
    return DIGITS.get(metric, 3)


def row_name(metric: str) -> str:
    """The Metric column's text of ``metric`` (``goal`` -> ``goal rate``)."""
    return ROW_NAMES.get(metric, metric)


NO_INTERVAL = "n = 1: no interval"


def cell(metric: str, mean: float, lo: float, hi: float, n: int, episodes: int) -> str:
    """'mean [low, high]' (the 95% interval's two ends: a bootstrap interval need not be
    symmetric, and a ± would imply values the data cannot have); one value has no interval:
    its mean alone when every cell of its column has one episode (the table's note says so),
    else 'mean (n = 1: no interval)'; ' (n=k)' when the metric applied in k of the episodes;
    '-' / '--' when it never applied."""
    if n == 0:
        return "--" if metric == "TTFC" else "-"
    d = _digits(metric)
    if n == 1:
        return f"{mean:.{d}f}" if episodes == 1 else f"{mean:.{d}f} ({NO_INTERVAL})"
    text = f"{mean:.{d}f} [{lo:.{d}f}, {hi:.{d}f}]"
    return text + (f" (n={n})" if n != episodes else "")


REFERENCE_COLUMNS = ("autopilot", "autopilot-discrete", "safe-non-turner", "random")
"""Reference policies (eval/testing/validity.py) shown as Table RQ1 columns beside the
algorithms, in Scenario 1 whose conditions they ran under; the rest of the degenerate suite is
one column, its strongest policy by driving score in each environment (by return where the
references have no DS: :data:`BEST_DEGENERATE`)."""
BEST_DEGENERATE = "best degenerate"
REF = "ref:"
"""Prefix of a reference column's key in :func:`wide_rows`' columns (``ref:autopilot``)."""


def reference_columns(refs: pd.DataFrame | None) -> list[str]:
    """The reference columns ``refs`` (eval.testing.session.reference_rows) fills, in order."""
    if refs is None or refs.empty:
        return []
    have = set(refs["policy"])
    cols = [p for p in REFERENCE_COLUMNS if p in have]
    return cols + ([BEST_DEGENERATE] if have - set(REFERENCE_COLUMNS) - _NOT_DEGENERATE else [])


_NOT_DEGENERATE = {"autopilot", "autopilot-discrete", "safe-non-turner"}


def strongest(pool: pd.DataFrame) -> str:
    """The policy (index) of ``pool`` with the highest mean DS, the return breaking ties (and
    deciding alone where the rows have no DS: references measured before the driving score)."""
    ds = pool["DS"].astype(float) if "DS" in pool else pd.Series(np.nan, index=pool.index)
    ret = pool["return"].astype(float)
    if ds.notna().any():
        return str(pd.DataFrame({"DS": ds.fillna(-np.inf), "return": ret})
                   .sort_values(["DS", "return"], ascending=False, kind="stable").index[0])
    return str(ret.idxmax())


def reference_rows(refs: pd.DataFrame | None):
    """(env, column, policy, its summary row) for every reference column ``refs`` fills in each
    environment; the best-degenerate column's policy is that environment's :func:`strongest`."""
    if refs is None or refs.empty:
        return
    for env, g in refs.groupby("env", sort=False):
        g = g.set_index("policy")
        for col in reference_columns(refs):
            name = col
            if col == BEST_DEGENERATE:
                pool = g.loc[[p for p in g.index if p not in REFERENCE_COLUMNS and p not in _NOT_DEGENERATE]]
                if pool.empty:
                    continue
                name = strongest(pool)
            if name in g.index:
                yield env, col, name, g.loc[name]


def reference_cells(refs: pd.DataFrame | None, metrics: Sequence[str] = TABLE_METRICS) -> dict:
    """(env, column) -> {metric: printed mean, "n (episodes)": the AC-episodes}; the
    reference rows are means over episodes x ACs (no interval: eval.testing.validity.summarize)."""
    out: dict = {}
    for env, col, name, r in reference_rows(refs):
        cells = {"n (episodes)": (f"{name}, " if col == BEST_DEGENERATE else "")
                 + f"{int(r['n'])} AC-episodes"}
        for m in metrics:
            v = float(r[m]) if m in r.index else float("nan")
            cells[m] = (f"{v:.{_digits(m)}f}" if np.isfinite(v) else "--" if m == "TTFC"
                        else "-" if m in r.index else "")
        out[(env, col)] = cells
    return out
