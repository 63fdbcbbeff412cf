"""Figures of the ANOVA report, rendered to PNG bytes with matplotlib's Agg canvas.

No pyplot and no global backend state: each function builds a ``matplotlib.figure.Figure``
and returns its PNG encoding, so callers decide where (and whether) the bytes are written.
"""

from __future__ import annotations

import io
from collections.abc import Sequence

import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from scipy import stats as sps

from wbc_jax.analysis.interaction import emm_table, interaction_shape, interaction_views

DPI = 110
PANEL = (3.2, 2.5)  # inches per subplot (w, h)
PANEL_INTERACTION = (4.4, 3.0)  # inches per interaction subplot: its legend sits right of the data
MIN_WIDTH = 6.0  # narrowest figure [in] (660 px at DPI)
MAX_ASPECT = 3.0  # longest side / shortest side of a figure
MAX_COLUMNS = 3  # panels per row of the means and success-rate figures


def _label(v) -> str:
    return f"{v:g}" if isinstance(v, (float, np.floating)) else str(v)


def _png(fig: Figure) -> bytes:
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return buf.getvalue()


def _axes(nrows: int, ncols: int, panel: tuple[float, float] = PANEL) -> tuple[Figure, np.ndarray]:
    """A figure of ``nrows`` x ``ncols`` panels of ``panel`` inches, at least :data:`MIN_WIDTH` wide and with sides
    at most :data:`MAX_ASPECT` apart (the panels stretched where needed)."""
    width = max(panel[0] * ncols, MIN_WIDTH)
    height = max(panel[1] * nrows, width / MAX_ASPECT)
    width = max(width, height / MAX_ASPECT)
    fig = Figure(figsize=(width, height), layout="constrained")
    return fig, np.atleast_2d(fig.subplots(nrows, ncols, squeeze=False))


def _errorbars(a, x, t: pd.DataFrame, **kw) -> None:
    """EMMs of table ``t`` (columns emm, ci_low, ci_high) at positions ``x`` with their CIs (none where NaN)."""
    err = np.vstack([t["emm"] - t["ci_low"], t["ci_high"] - t["emm"]])
    a.errorbar(x, t["emm"], yerr=np.nan_to_num(err), marker="o", **kw)


def means_grid(emms: dict[str, dict[str, pd.DataFrame]], factors: Sequence[str], metrics: Sequence[str],
               labels: dict[str, str] | None = None) -> bytes:
    """EMM +- 95 % CI of each metric against each factor's levels: per metric, a row of up to
    :data:`MAX_COLUMNS` factors (more rows when there are more factors); the paper's Fig. 3.

    Args:
        emms: metric -> factor -> :func:`wbc_jax.analysis.stats.emmeans` table over that factor.
        labels: metric -> axis label (default: the metric's name).
    """
    labels = labels or {}
    ncols = min(len(factors), MAX_COLUMNS)
    rows_per = -(-len(factors) // ncols)
    fig, ax = _axes(len(metrics) * rows_per, ncols)
    for a in ax.flat:
        a.set_visible(False)
    for i, m in enumerate(metrics):
        for j, f in enumerate(factors):
            t = emms[m][f]
            a = ax[i * rows_per + j // ncols, j % ncols]
            a.set_visible(True)
            x = np.arange(len(t))
            _errorbars(a, x, t, capsize=4, lw=1.5)
            a.set_xticks(x, [_label(v) for v in t[f]])
            a.set_xlabel(f)
            if j % ncols == 0:
                a.set_ylabel(f"{labels.get(m, m)}, EMM (95 % CI)")
            a.grid(alpha=0.3)
    fig.suptitle("Estimated marginal means ± 95 % CI per factor level (successful runs)")
    return _png(fig)


def interaction_grid(emms: dict[str, dict[str, pd.DataFrame]], metrics: Sequence[str],
                     unreliable: Sequence[str] = (), labels: dict[str, str] | None = None) -> bytes | None:
    """EMM +- 95 % CI interaction plots, each two-way interaction in both orientations side by side (A on the x axis
    with a line per level of B, then B on x with a line per A), each titled ordinal or disordinal
    (:func:`interaction_shape`); per metric a block of rows, two interactions a row when there are more than
    four; legends right of the data; the paper's Fig. 4.

    Args:
        emms: metric -> {"A:B": :func:`wbc_jax.analysis.stats.emmeans` table over (A, B)}.
        unreliable: metrics whose F tests are unreliable (marked in the panel titles).
        labels: metric -> axis label (default: the metric's name).

    Returns:
        PNG bytes, or None when the model has no two-way interaction.
    """
    labels = labels or {}
    pairs = list(next(iter(emms.values())).keys()) if emms else []
    if not pairs:
        return None
    views = interaction_views(pairs)
    ncols = 2 if len(pairs) <= 4 else 4
    rows_per = -(-len(views) // ncols)
    fig, ax = _axes(len(metrics) * rows_per, ncols, PANEL_INTERACTION)
    for a in ax.flat[len(metrics) * len(views):]:
        a.set_visible(False)
    for i, m in enumerate(metrics):
        for j, (pair, xf, lf) in enumerate(views):
            a = ax[i * rows_per + j // ncols, j % ncols]
            _interaction_panel(a, emms[m][pair], xf, lf, labels.get(m, m))
            if m in unreliable:
                a.set_title(a.get_title() + " (F tests unreliable)", fontsize=9)
    what = f"{labels.get(metrics[0], metrics[0])}: e" if len(metrics) == 1 else "E"
    fig.suptitle(f"{what}stimated marginal means ± 95 % CI (interaction plots, both orientations)")
    return _png(fig)


def _interaction_panel(a, t: pd.DataFrame, xf: str, lf: str, label: str) -> None:
    """One interaction plot: ``xf``'s levels on the x axis, a line per level of ``lf`` (slightly offset)."""
    xs = list(dict.fromkeys(t[xf]))
    n_lines = t[lf].nunique()
    for k, (lv, g) in enumerate(t.groupby(lf, sort=False)):
        pos = np.array([xs.index(v) for v in g[xf]]) + (k - (n_lines - 1) / 2) * 0.04
        _errorbars(a, pos, g, capsize=3, lw=1.3, label=_label(lv))
    a.set_xticks(np.arange(len(xs)), [_label(v) for v in xs])
    a.set_xlabel(xf)
    a.set_ylabel(f"{label}, EMM (95 % CI)")
    shape = interaction_shape(emm_table(t, xf, lf).to_numpy())
    a.set_title(f"{xf} × {lf}: {shape}", fontsize=9)
    a.legend(title=lf, fontsize=7, title_fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0),
             borderaxespad=0.0)
    a.grid(alpha=0.3)


def qq_grid(residuals: dict[str, tuple[np.ndarray, float]]) -> bytes:
    """Normal Q-Q plots of standardized residuals (residual / sqrt(MSE)), one panel per metric.

    Args:
        residuals: metric -> (residuals, MSE); MSE None when the residuals are numerically zero.
    """
    n = len(residuals)
    ncols = min(n, 3)
    nrows = -(-n // ncols)
    fig, ax = _axes(nrows, ncols)
    for a in ax.flat[n:]:
        a.set_visible(False)
    for a, (m, (r, mse)) in zip(ax.flat, residuals.items()):
        r = np.asarray(r, float)
        a.set_title(m)
        if mse is None or not np.isfinite(mse) or mse <= 0 or np.ptp(r) == 0:
            a.text(0.5, 0.5, "residuals ≈ 0\n(no Q-Q plot)", ha="center", va="center", transform=a.transAxes)
            continue
        (osm, osr), _ = sps.probplot(r / np.sqrt(mse), dist="norm")
        a.plot(osm, osr, ".", ms=4)
        lim = [min(osm.min(), osr.min()), max(osm.max(), osr.max())]
        a.plot(lim, lim, "k--", lw=1)
        a.set_xlabel("normal quantile")
        a.set_ylabel("standardized residual")
        a.grid(alpha=0.3)
    fig.suptitle("Residual normal Q-Q plots")
    return _png(fig)


def success_levels(rates: pd.DataFrame, factors: Sequence[str]) -> bytes:
    """Success rate [%] (all runs) against each factor's levels, one panel per factor (up to :data:`MAX_COLUMNS` a
    row).

    Args:
        rates: :func:`wbc_jax.analysis.success.by_level` output.
    """
    ncols = min(len(factors), MAX_COLUMNS)
    fig, ax = _axes(-(-len(factors) // ncols), ncols)
    for a in ax.flat[len(factors):]:
        a.set_visible(False)
    for a, f in zip(ax.flat, factors):
        t = rates[rates["factor"] == f]
        x = np.arange(len(t))
        a.plot(x, 100 * t["rate"], "o-")
        a.set_xticks(x, [_label(v) for v in t["level"]])
        a.set_ylim(-5, 105)
        a.set_xlabel(f)
        a.set_ylabel("success rate [%]")
        a.grid(alpha=0.3)
    fig.suptitle("Success rate per factor level (all runs)")
    return _png(fig)


def success_pairs(tables: dict[tuple[str, str], pd.DataFrame]) -> bytes:
    """Heatmaps of the success rate [%] of each pair of factors (all runs), cells annotated successes/runs.

    Args:
        tables: (a, b) -> :func:`wbc_jax.analysis.success.by_pair` output.
    """
    n = len(tables)
    ncols = min(n, 3)
    fig, ax = _axes(-(-n // ncols), ncols)
    for a in ax.flat[n:]:
        a.set_visible(False)
    for a, ((f, g), t) in zip(ax.flat, tables.items()):
        ya, xb = list(pd.unique(t[f])), list(pd.unique(t[g]))
        rate = t.pivot(index=f, columns=g, values="rate").reindex(index=ya, columns=xb)
        im = a.imshow(100 * rate.to_numpy(float), vmin=0, vmax=100, cmap="RdYlGn", origin="lower", aspect="auto")
        for (i, j), r in np.ndenumerate(t.pivot(index=f, columns=g, values="runs").reindex(index=ya, columns=xb)
                                        .to_numpy()):
            s = t[(t[f] == ya[i]) & (t[g] == xb[j])]["successes"].iloc[0]
            a.text(j, i, f"{s}/{r}", ha="center", va="center", fontsize=7)
        a.set_xticks(np.arange(len(xb)), [_label(v) for v in xb])
        a.set_yticks(np.arange(len(ya)), [_label(v) for v in ya])
        a.set_xlabel(g)
        a.set_ylabel(f)
    fig.colorbar(im, ax=ax.ravel().tolist(), label="success rate [%]", shrink=0.8)
    fig.suptitle("Success rate per pair of factors (all runs; cells: successes/runs)")
    return _png(fig)


def warm_up() -> bytes:
    """Draw one small figure with the calls the report's figures make (a process's first figure loads fonts and
    the canvas); figure workers call it as they start."""
    t = pd.DataFrame({"a": [0.1, 0.1, 0.2, 0.2], "b": [1, 2, 1, 2], "emm": [0.0, 1.0, 0.5, 1.5]})
    t["ci_low"], t["ci_high"] = t["emm"] - 0.1, t["emm"] + 0.1
    fig, ax = _axes(2, 2, PANEL_INTERACTION)
    for a in ax.flat:
        _interaction_panel(a, t, "a", "b", "R")
    fig.suptitle("warm-up")
    return _png(fig)
