"""Figures of the paper's studies (matplotlib, written as PNG; no screen needed)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

__all__ = ['COLORS', 'LABELS', 'centerline_shapes', 'error_bars', 'errors_vs_r', 'output_traces']

COLORS = {'lopinf': 'tab:red', 'dmdc': 'tab:green', 'era': 'tab:blue', 'fom': 'black',
          'lopinf_cubic': 'tab:purple'}
LABELS = {'lopinf': 'LOpInf', 'dmdc': 'DMDc', 'era': 'ERA/OKID', 'fom': 'FOM',
          'lopinf_cubic': 'LOpInf cubic'}


def _plt():
    import matplotlib
    matplotlib.use('Agg', force=False)
    import matplotlib.pyplot as plt
    return plt


def errors_vs_r(path: Path, curves: Mapping[str, Mapping[str, Sequence[float]]], *,
                paper: Mapping[str, Mapping[str, Sequence[float]]] | None = None,
                metric_label: str = 'Relative output error') -> Path:
    """Paper Fig. 2: training and test error against r, one panel per method.

    Parameters
    ----------
    curves : dict
        ``method -> {'r': [...], 'train': [...], 'test': [...]}``.
    paper : dict, optional
        The paper's numbers in the same layout, drawn faintly for reference.
    """
    plt = _plt()
    methods = [m for m in ('lopinf', 'dmdc', 'era', 'lopinf_cubic') if m in curves]
    fig, axes = plt.subplots(1, len(methods), figsize=(4.2 * len(methods), 3.4), sharey=True,
                             squeeze=False)
    for ax, method in zip(axes[0], methods):
        c = curves[method]
        color = COLORS[method]
        ax.semilogy(c['r'], c['train'], ':o', color=color, label='training (ours)')
        ax.semilogy(c['r'], c['test'], '-.^', color=color, label='test (ours)')
        if paper and method in paper:
            p = paper[method]
            ax.semilogy(p['r'], p['train'], ':o', color='0.6', ms=3, lw=1,
                        label='training (paper)')
            ax.semilogy(p['r'], p['test'], '-.^', color='0.6', ms=3, lw=1, label='test (paper)')
        ax.set_title(LABELS[method])
        ax.set_xlabel('reduced dimension r')
        ax.grid(True, which='both', alpha=0.3)
        ax.legend(fontsize=7)
    axes[0][0].set_ylabel(metric_label)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def output_traces(path: Path, t: NDArray[np.float64], fom: NDArray[np.float64],
                  roms: Mapping[str, NDArray[np.float64]], rows: Sequence[int],
                  row_names: Sequence[str], *, t_split: float | None = None,
                  rom_labels: Mapping[str, str] | None = None, scale: float = 1e3,
                  unit: str = 'mm') -> Path:
    """Paper Fig. 3: chosen outputs of the FOM and the ROMs against time.

    Parameters
    ----------
    t : ndarray, shape (k,)
    fom : ndarray, shape (p, k)
    roms : dict
        ``method -> Ŷ (p, k)``.
    rows : sequence of int
        Output indices to draw (one panel each).
    t_split : float, optional
        End of training, drawn as a vertical magenta line.
    """
    plt = _plt()
    fig, axes = plt.subplots(len(rows), 1, figsize=(7.5, 2.4 * len(rows)), sharex=True,
                             squeeze=False)
    for ax, row, name in zip(axes[:, 0], rows, row_names):
        ax.plot(t, fom[row] * scale, color=COLORS['fom'], lw=2.0, label='FOM')
        styles = {'lopinf': ':', 'dmdc': '-.', 'era': '--', 'lopinf_cubic': '-'}
        for method, Y in roms.items():
            label = (rom_labels or {}).get(method, LABELS.get(method, method))
            ax.plot(t, Y[row] * scale, styles.get(method, '-'), color=COLORS.get(method),
                    lw=1.6, label=label)
        if t_split is not None:
            ax.axvline(t_split, color='magenta', lw=1.5)
        lo, hi = float(np.min(fom[row])) * scale, float(np.max(fom[row])) * scale
        pad = max(hi - lo, 1e-9)
        ax.set_ylim(lo - 0.5 * pad, hi + 0.5 * pad)  # a diverging ROM must not hide the FOM
        ax.set_ylabel(f'{name} [{unit}]')
        ax.grid(True, alpha=0.3)
    axes[0, 0].legend(fontsize=8, ncol=4, loc='upper left')
    axes[-1, 0].set_xlabel('time [s]')
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def error_bars(path: Path, errors: Mapping[str, Mapping[str, float]], *,
               paper: Mapping[str, Mapping[str, float]] | None = None,
               rom_labels: Mapping[str, str] | None = None,
               metric_label: str = 'Relative output error') -> Path:
    """Paper Fig. 4: bar chart of test errors per episode and method.

    Parameters
    ----------
    errors : dict
        ``method -> {episode -> error}``.
    """
    plt = _plt()
    methods = [m for m in ('lopinf', 'dmdc', 'era', 'lopinf_cubic') if m in errors]
    episodes = list(next(iter(errors.values())).keys())
    x = np.arange(len(episodes))
    width = 0.8 / len(methods)
    fig, ax = plt.subplots(figsize=(7.5, 3.4))
    for i, method in enumerate(methods):
        vals = [errors[method][ep] for ep in episodes]
        label = (rom_labels or {}).get(method, LABELS[method])
        ax.bar(x + (i - (len(methods) - 1) / 2) * width, vals, width, color=COLORS[method],
               label=label)
        if paper and method in paper:
            pv = [paper[method].get(ep, np.nan) for ep in episodes]
            ax.plot(x + (i - (len(methods) - 1) / 2) * width, pv, 'k_', ms=14, mew=2,
                    label='paper' if i == 0 else None)
    ax.set_xticks(x)
    ax.set_xticklabels([ep.replace('ep', 'Ep ') for ep in episodes])
    ax.set_ylabel(metric_label)
    ax.set_xlabel('test episodes')
    ax.grid(True, axis='y', alpha=0.3)
    ax.legend(fontsize=8, ncol=4)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def centerline_shapes(path: Path, times: Sequence[float],
                      shapes: Mapping[str, Sequence[tuple[NDArray[np.float64],
                                                          NDArray[np.float64]]]], *,
                      rom_labels: Mapping[str, str] | None = None, scale: float = 1e3) -> Path:
    """Paper Fig. 5: centerline x–z shapes (mm) of the FOM and the ROMs at given times.

    Parameters
    ----------
    times : sequence of float
        One panel per time.
    shapes : dict
        ``'fom' | method -> [(x (N,), z (N,)) per time]`` in metres.
    """
    plt = _plt()
    fig, axes = plt.subplots(len(times), 1, figsize=(7.5, 2.3 * len(times)), sharex=True,
                             squeeze=False)
    markers = {'fom': '^-', 'lopinf': 'o:', 'dmdc': '*-.', 'era': '+--', 'lopinf_cubic': 's-'}
    for i, (ax, tt) in enumerate(zip(axes[:, 0], times)):
        for key, per_time in shapes.items():
            x, z = per_time[i]
            label = (rom_labels or {}).get(key, LABELS.get(key, key))
            ax.plot(np.asarray(x) * scale, np.asarray(z) * scale, markers.get(key, '-'),
                    color=COLORS.get(key), lw=1.5, ms=4, label=label)
        fx, fz = (np.asarray(a) * scale for a in shapes['fom'][i]) if 'fom' in shapes else (
            np.zeros(1), np.zeros(1))
        zpad = max(float(np.max(np.abs(fz))), 1e-3 * scale * 5)
        ax.set_ylim(-2.0 * zpad, 2.0 * zpad)  # a diverging ROM must not hide the FOM
        ax.set_xlim(float(np.min(fx)) - 0.05 * np.ptp(fx) - 1, float(np.max(fx))
                    + 0.05 * np.ptp(fx) + 1)
        ax.set_title(f't = {tt:g} s', fontsize=9)
        ax.set_ylabel('z [mm]')
        ax.grid(True, alpha=0.3)
    axes[0, 0].legend(fontsize=8, ncol=4)
    axes[-1, 0].set_xlabel('x [mm]')
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
