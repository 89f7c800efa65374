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


def energy_error_plot(series: dict, path, title: str, time_label: str = "t",
                      angular_momentum: dict | None = None) -> Path:
    """Relative energy error against time, log scale, one line per method; with
    ``angular_momentum``, the relative change of the angular momentum in a second panel beside it.

    Parameters
    ----------
    series : dict
        label -> (t (n,), relative energy error (n,)).
    path : str or Path
        Where to write the PNG.
    title, time_label : str
    angular_momentum : dict, optional
        label -> (t (n,), |L - L0| / |L0| (n,)) (the ``angular_momentum_series`` of
        :func:`hbvm_md.compare_rebound` and :func:`hbvm_md.compare_md`).

    Returns
    -------
    Path of the PNG.  The series may be signed (H - H0) / |H0|: the magnitude is drawn, so that
    a negative error is not hidden below the axis.  Zeros are drawn at 1e-17 (below double
    round-off) so they stay visible.
    """
    plt = _pyplot()
    panels = [(series, "|H - H0| / |H0|")]
    if angular_momentum:
        panels.append((angular_momentum, "|L - L0| / |L0|"))
    fig, axes = plt.subplots(1, len(panels), figsize=(7 * len(panels), 4.2), dpi=120, squeeze=False)
    for ax, (data, ylabel) in zip(axes[0], panels):
        for label, (t, err) in data.items():
            ax.semilogy(np.asarray(t), plotted_error(err), label=label, lw=1)
        ax.set_xlabel(time_label)
        ax.set_ylabel(ylabel)
        ax.grid(True, which="major", alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    if len(panels) == 1:
        axes[0, 0].set_title(title)
    else:
        fig.suptitle(title)
    return _save(fig, path)


def work_precision_plot(rows: list, path, title: str) -> Path:
    """Work-precision diagram: error against wall time, energy error (left), the angular
    momentum's relative change (middle, on scenes where it is an invariant: rows with a finite
    ``max_rel_angular_momentum_error``) and solution error (right), one line per method (rows of
    :func:`hbvm_md.reports.workprecision.sweep`).

    Unfinished runs are left out.  Returns the PNG path.
    """
    plt = _pyplot()
    keys = ["max_rel_energy_error", "solution_error"]
    labels = ["max relative energy error", "final solution error (vs reference)"]
    if any(np.isfinite(r.get("max_rel_angular_momentum_error", np.nan)) for r in rows):
        keys.insert(1, "max_rel_angular_momentum_error")
        labels.insert(1, "max relative angular momentum error")
    fig, axes = plt.subplots(1, len(keys), figsize=(5.5 * len(keys), 4.4), dpi=120)
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
        for ax, key in zip(axes, keys):
            v = np.clip([r.get(key, np.nan) for r in rs], 1e-17, None)
            ax.loglog(w, v, marker=markers[i % len(markers)], ms=4, lw=1, label=m)
    for ax, lab in zip(axes, labels):
        ax.set_xlabel("wall time [s]")
        ax.set_ylabel(lab)
        ax.grid(True, which="major", alpha=0.3)
    axes[-1].legend(fontsize=7, loc="best")
    fig.suptitle(title)
    return _save(fig, path)
