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


def _label(v) -> str:
    return f"{v:g}" if isinstance(v, (float, np.floating)) else str(v)


def _png(fig: Figure) -> bytes:
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return buf.getvalue()


def _axes(nrows: int, ncols: int) -> tuple[Figure, np.ndarray]:
    fig = Figure(figsize=(PANEL[0] * ncols, PANEL[1] * nrows), layout="constrained")
    return fig, np.atleast_2d(fig.subplots(nrows, ncols, squeeze=False))


def means_grid(level_means: pd.DataFrame, factors: Sequence[str], metrics: Sequence[str]) -> bytes:
    """Mean +- SD of each metric (rows) against each factor's levels (columns); the paper's Fig. 3.

    Args:
        level_means: :func:`wbc_jax.analysis.stats.level_means` output.
    """
    fig, ax = _axes(len(metrics), len(factors))
    for i, m in enumerate(metrics):
        for j, f in enumerate(factors):
            t = level_means[(level_means["metric"] == m) & (level_means["factor"] == f)]
            a = ax[i, j]
            x = np.arange(len(t))
            a.errorbar(x, t["mean"], yerr=t["sd"].fillna(0), marker="o", capsize=4, lw=1.5)
            a.set_xticks(x, [_label(v) for v in t["level"]])
            a.set_xlabel(f)
            if j == 0:
                a.set_ylabel(f"{m} (mean ± SD)")
            a.grid(alpha=0.3)
    fig.suptitle("Metric means ± SD per factor level (successful runs)")
    return _png(fig)


def interaction_grid(emms: dict[str, dict[str, pd.DataFrame]], metrics: Sequence[str],
                     unreliable: Sequence[str] = ()) -> bytes | None:
    """EMM +- 95 % CI interaction plots: rows metrics, columns each two-way interaction in both orientations (A on
    the x axis with a line per level of B, then B on x with a line per A), each titled ordinal or disordinal
    (:func:`interaction_shape`); the paper's Fig. 4.

    Args:
        emms: metric -> {"A:B": :func:`wbc_jax.analysis.stats.emmeans` table over (A, B)}.
        unreliable: metrics whose F tests are unreliable (marked in the panel titles).

    Returns:
        PNG bytes, or None when the model has no two-way interaction.
    """
    pairs = list(next(iter(emms.values())).keys()) if emms else []
    if not pairs:
        return None
    views = interaction_views(pairs)
    fig, ax = _axes(len(metrics), len(views))
    for i, m in enumerate(metrics):
        for j, (pair, xf, lf) in enumerate(views):
            t = emms[m][pair]
            a = ax[i, j]
            xs = list(dict.fromkeys(t[xf]))
            n_lines = t[lf].nunique()
            for k, (lv, g) in enumerate(t.groupby(lf, sort=False)):
                pos = np.array([xs.index(v) for v in g[xf]]) + (k - (n_lines - 1) / 2) * 0.04
                err = np.vstack([g["emm"] - g["ci_low"], g["ci_high"] - g["emm"]])
                a.errorbar(pos, g["emm"], yerr=err, marker="o", capsize=3, lw=1.3, label=f"{lf}={_label(lv)}")
            a.set_xticks(np.arange(len(xs)), [_label(v) for v in xs])
            a.set_xlabel(xf)
            a.set_ylabel(f"{m} EMM (95% CI)" if j == 0 else "")
            shape = interaction_shape(emm_table(t, xf, lf).to_numpy())
            a.set_title(f"{m}: {xf} × {lf}, {shape}" + (" (F tests unreliable)" if m in unreliable else ""),
                        fontsize=9)
            a.legend(fontsize=7, framealpha=0.6)
            a.grid(alpha=0.3)
    fig.suptitle("Estimated marginal means ± 95 % CI (interaction plots, both orientations)")
    return _png(fig)


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
    """Success rate [%] (all runs) against each factor's levels, one panel per factor.

    Args:
        rates: :func:`wbc_jax.analysis.success.by_level` output.
    """
    fig, ax = _axes(1, len(factors))
    for a, f in zip(ax[0], factors):
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
    fig, ax = _axes(2, 2)
    for a in ax.flat:
        a.errorbar([0.0, 1.0], [0.0, 1.0], yerr=[[0.1, 0.1], [0.1, 0.1]], marker="o", capsize=3, lw=1.3,
                   label="a=1")
        a.set_xticks([0, 1], ["0.1", "0.2"])
        a.set_xlabel("a")
        a.set_ylabel("R EMM (95% CI)")
        a.set_title("R: a × b, ordinal", fontsize=9)
        a.legend(fontsize=7, framealpha=0.6)
        a.grid(alpha=0.3)
    fig.suptitle("warm-up")
    return _png(fig)
