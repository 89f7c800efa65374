"""PNG figures of the reports (matplotlib, Agg backend: no display needed)."""
from __future__ import annotations

from pathlib import Path

import numpy as np


def _save(fig, path) -> Path:
    """Lay out, write (creating the folder) and close a figure; returns the path."""
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    _pyplot().close(fig)
    return path

def _pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def plotted_error(err) -> np.ndarray:
    """|err| with non-finite values as gaps (nan) and zeros lifted to 1e-17 for a log axis."""
    err = np.abs(np.asarray(err, dtype=float))
    return np.clip(np.where(np.isfinite(err), err, np.nan), 1e-17, None)


def energy_error_plot(series: dict, path, title: str, time_label: str = "t") -> Path:
    """Relative energy error against time, log scale, one line per method.

    Parameters
    ----------
    series : dict
        label -> (t (n,), relative energy error (n,)).
    path : str or Path
        Where to write the PNG.
    title, time_label : str

    Returns
    -------
    Path of the PNG.  The series may be signed (H - H0) / |H0|: the magnitude is drawn, so that
    a negative error is not hidden below the axis.  Zeros are drawn at 1e-17 (below double
    round-off) so they stay visible.
    """
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.2), dpi=120)
    for label, (t, err) in series.items():
        ax.semilogy(np.asarray(t), plotted_error(err), label=label, lw=1)
    ax.set_xlabel(time_label)
    ax.set_ylabel("|H - H0| / |H0|")
    ax.set_title(title)
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    return _save(fig, path)


def work_precision_plot(rows: list, path, title: str) -> Path:
    """Work-precision diagram: error against wall time, energy error (left) and solution error
    (right), one line per method (rows of :func:`hbvm_md.reports.workprecision.sweep`).

    Unfinished runs are left out.  Returns the PNG path.
    """
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4), dpi=120)
    methods = []
    for r in rows:
        if r["method"] not in methods:
            methods.append(r["method"])
    markers = "os^vD<>pPX*h"
    for i, m in enumerate(methods):
        rs = sorted((r for r in rows if r["method"] == m and r["finished"]), key=lambda r: r["wall_time_s"])
        if not rs:
            continue
        w = [max(r["wall_time_s"], 1e-6) for r in rs]
        for ax, key in zip(axes, ("max_rel_energy_error", "solution_error")):
            v = np.clip([r[key] for r in rs], 1e-17, None)
            ax.loglog(w, v, marker=markers[i % len(markers)], ms=4, lw=1, label=m)
    for ax, lab in zip(axes, ("max relative energy error", "final solution error (vs reference)")):
        ax.set_xlabel("wall time [s]")
        ax.set_ylabel(lab)
        ax.grid(True, which="major", alpha=0.3)
    axes[1].legend(fontsize=7, loc="best")
    fig.suptitle(title)
    return _save(fig, path)
