"""Figures of the paper's studies and of ``evaluate --plots`` (matplotlib PNG, no screen needed).

Every figure is drawn for the width a report shows it at (7.5 in at 120 dpi: 900 px) and
says what it shows without the code: a title naming the study, the split and the episode,
one legend above the panels (never over the data), integer ``r`` ticks, lengths in mm, and
exact model labels (method, variant, forces, r). A curve or point that leaves the axis
range is cut at the edge and marked there with a triangle in its colour (``▲`` above,
``▼`` below), listed in the legend as off the scale, instead of running off the axes.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
import textwrap
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ['COLORS', 'LABELS', 'centerline_shapes', 'error_bars', 'errors_vs_r',
           'model_label', 'output_traces']

COLORS = {'lopinf': 'tab:red', 'dmdc': 'tab:green', 'era': 'tab:blue', 'fom': 'black',
          'lopinf_cubic': 'tab:purple'}
LABELS = {'lopinf': 'LOpInf', 'dmdc': 'DMDc', 'era': 'ERA/OKID', 'fom': 'FOM',
          'lopinf_cubic': 'LOpInf cubic'}
METHOD_ORDER = ('lopinf', 'dmdc', 'era', 'lopinf_cubic')
STYLES = {'lopinf': ':', 'dmdc': '-.', 'era': '--', 'lopinf_cubic': '-'}

WIDTH_IN, DPI = 7.5, 120          # 900 px: the width a Markdown viewer shows a figure at
_OFF: dict[str, Any] = dict(ls='none', ms=7, clip_on=False, zorder=5)


def model_label(model: Any) -> str:
    """``'LOpInf r=4'``, ``'LOpInf cubic r=4'``, ``'DMDc stable r=8'``, ``'ERA/OKID r=20'``.

    Method, variant (DMDc, when not the paper's), forces (LOpInf, when cubic) and ``r``, from
    the model and its metadata; a model that is none of these is named by its ``method``.
    """
    meta = getattr(model, 'metadata', {}) or {}
    method = str(getattr(model, 'method', ''))
    words = [LABELS.get(method, method)]
    if method == 'lopinf' and getattr(model, 'is_nonlinear', False):
        words.append('cubic')
    variant = meta.get('variant') if method == 'dmdc' else None
    if variant not in (None, '', 'paper'):
        words.append(str(variant))
    r = meta.get('r') if method == 'dmdc' and isinstance(meta.get('r'), int) else model.r
    words.append(f'r={r}')
    return ' '.join(words)


def _plt() -> Any:
    import matplotlib
    matplotlib.use('Agg', force=False)
    import matplotlib.pyplot as plt
    return plt


#: What :func:`_plot_in_range` returns: bits of the edges a curve was cut at.
ABOVE, BELOW = 1, 2


def _off_handles(plt: Any, sides: int = ABOVE) -> tuple[list[Any], list[str]]:
    """Legend entries of the edge markers that were drawn (``sides``: ABOVE | BELOW)."""
    from matplotlib.lines import Line2D
    handles, labels = [], []
    for bit, marker, where in ((ABOVE, '^', 'above'), (BELOW, 'v', 'below')):
        if sides & bit:
            handles.append(Line2D([], [], marker=marker, color='0.4', **_OFF))
            labels.append(f'{where} the scale (cut at the edge)')
    return handles, labels


def _finish(fig: Any, path: Path, title: str, handles: Sequence[Any], labels: Sequence[str],
            *, ncol: int) -> Path:
    """Title and legend above the panels, laid out without overlap, written as PNG."""
    plt = _plt()
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    height = fig.bbox.height
    top = 1.0
    if title:     # fig.text, not suptitle: tight_layout would make room for it twice
        head = fig.text(0.5, 0.995, textwrap.fill(title, 95), fontsize=9.5, ha='center',
                        va='top')
        top -= head.get_window_extent(renderer).height / height + 0.01
    if handles:
        leg = fig.legend(handles, labels, loc='upper center', bbox_to_anchor=(0.5, top),
                         ncol=ncol, fontsize=8, frameon=False, columnspacing=1.2,
                         handlelength=2.6)
        top -= leg.get_window_extent(renderer).height / height + 0.005
    fig.tight_layout(rect=(0.0, 0.0, 1.0, max(top, 0.5)))
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def _legend_entries(axes: Sequence[Any]) -> tuple[list[Any], list[str]]:
    """Handles and labels of every panel, each label once, in order of appearance."""
    handles, labels = [], []
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels()):
            if lab not in labels and not lab.startswith('_'):
                handles.append(h)
                labels.append(lab)
    return handles, labels


def _plot_in_range(ax: Any, x: Any, y: Any, lo: float,
                   hi: float, *, log: bool = False, points: bool = False,
                   **style: Any) -> int:
    """Plot ``y(x)`` cut where it leaves ``[lo, hi]``: the line ends at the edge, marked there.

    Returns the edges it was cut at (:data:`ABOVE` | :data:`BELOW`, 0 if none). A non-finite
    value counts as above the range. With ``log`` the crossings are interpolated in log10
    (for a logarithmic axis). With ``points`` (data at discrete ``x``, e.g. orders r) every
    point outside is marked at its own ``x`` on the edge; otherwise (a sampled curve) the
    marks are where the curve leaves the range.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    with np.errstate(divide='ignore', invalid='ignore'):
        fy = np.log10(y) if log else y.copy()
    flo, fhi = (np.log10(lo), np.log10(hi)) if log else (lo, hi)
    finite = np.isfinite(fy)
    side = np.where(~finite | (fy > fhi), 1, np.where(fy < flo, -1, 0))
    edge = {1: fhi, -1: flo}
    xs: list[float] = []
    ys: list[float] = []
    exits: list[tuple[float, int]] = []

    def cross(i: int, level: float) -> float:
        if not (finite[i] and finite[i - 1]) or fy[i] == fy[i - 1]:
            return float(x[i - 1] if finite[i - 1] else x[i])
        w = (level - fy[i - 1]) / (fy[i] - fy[i - 1])
        return float(x[i - 1] + w * (x[i] - x[i - 1]))

    if not len(x):
        return 0
    if side[0] == 0:
        xs.append(x[0])
        ys.append(fy[0])
    else:
        exits.append((float(x[0]), int(side[0])))
    for i in range(1, len(x)):
        a, b = int(side[i - 1]), int(side[i])
        if a == b and a != 0:
            continue
        if a != 0:                                   # comes back in (through edge a)
            xs.append(cross(i, edge[a]))
            ys.append(edge[a])
        if b == 0:
            xs.append(x[i])
            ys.append(fy[i])
        else:                                        # leaves (through edge b)
            xc = cross(i, edge[b])
            xs += [xc, np.nan]
            ys += [edge[b], np.nan]
            exits.append((xc, b))
    ys_arr = np.asarray(ys, dtype=np.float64)
    marker = style.pop('marker', None)
    ms = style.pop('ms', None)
    label = style.pop('label', None)
    line = ax.plot(np.asarray(xs, dtype=np.float64), 10.0 ** ys_arr if log else ys_arr,
                   **style)[0]
    color = line.get_color()
    if marker is not None:          # markers on the data points only, not on the cuts
        inside = side == 0
        ax.plot(x[inside], y[inside], ls='none', marker=marker, ms=ms, color=color)
    ax.plot([], [], marker=marker, ms=ms, label=label, **dict(style, color=color))
    if points:
        exits = [(float(xi), int(si)) for xi, si in zip(x, side) if si != 0]
    for xe, s in exits:
        ax.plot([xe], [hi if s > 0 else lo], marker='^' if s > 0 else 'v',
                color=color, **_OFF)
    return (ABOVE if any(s > 0 for _, s in exits) else 0) | (
        BELOW if any(s < 0 for _, s in exits) else 0)


def _r_ticks(ax: Any, rs: Sequence[float]) -> None:
    """Ticks at the orders drawn (every other one beyond 8), else integers."""
    ticks = sorted({int(r) for r in rs})
    if not ticks:
        from matplotlib.ticker import MaxNLocator
        ax.xaxis.set_major_locator(MaxNLocator(integer=True, nbins=6))
        return
    while len(ticks) > 8:
        ticks = ticks[::2]
    ax.set_xticks(ticks)


def errors_vs_r(path: Path, curves: Mapping[str, Mapping[str, Sequence[float]]], *,
                paper: Mapping[str, Mapping[str, Sequence[float]]] | None = None,
                metric_label: str = 'Relative output error', title: str = '',
                y_max: float | None = None,
                labels: Mapping[str, str] | None = None) -> Path:
    """Paper Fig. 2: training and test error against r, one panel per method.

    The cubic LOpInf is drawn in the LOpInf panel (a variant of the same method, usually
    fitted at one r). Errors above ``y_max`` are marked at the top edge.

    Parameters
    ----------
    curves : dict
        ``method -> {'r': [...], 'train': [...], 'test': [...]}``.
    paper : dict, optional
        The paper's numbers in the same layout, drawn in grey for reference.
    title : str
        Which study, split and episode.
    y_max : float, optional
        Top of the (shared, logarithmic) error axis.
    labels : dict, optional
        ``method -> label`` (default :data:`LABELS`).
    """
    plt = _plt()
    names = dict(LABELS, **(labels or {}))
    panels = [m for m in ('lopinf', 'dmdc', 'era') if m in curves]
    if 'lopinf_cubic' in curves and 'lopinf' not in curves:
        panels.insert(0, 'lopinf_cubic')
    values = [v for c in curves.values() for k in ('train', 'test') for v in c[k]
              if np.isfinite(v) and v > 0]
    values += [v for m in panels for k in ('train', 'test')
               for v in (paper or {}).get(m, {}).get(k, [])]
    lo = 0.5 * min(values, default=1e-3)
    hi = max(values, default=1.0) * 2.0
    if y_max is not None:
        hi = min(hi, y_max)
    fig, axes = plt.subplots(1, len(panels), figsize=(WIDTH_IN, 3.3), sharey=True,
                             squeeze=False)
    cut = 0
    for ax, method in zip(axes[0], panels):
        drawn = [method] + (['lopinf_cubic'] if method == 'lopinf' and 'lopinf_cubic' in curves
                            else [])
        if paper and method in paper:
            p = paper[method]
            ax.plot(p['r'], p['train'], ':o', color='0.65', ms=3, lw=1, label='paper, training')
            ax.plot(p['r'], p['test'], '-.^', color='0.65', ms=3, lw=1, label='paper, test')
        for m in drawn:
            c = curves[m]
            for key, style, what in (('train', ':o', 'training'), ('test', '-.^', 'test')):
                cut |= _plot_in_range(ax, c['r'], c[key], lo, hi, log=True, points=True,
                                      marker=style[-1], ls=style[:-1], color=COLORS[m],
                                      ms=4.5, lw=1.4, label=f'{names[m]}, {what}')
        ax.set_yscale('log')
        ax.set_ylim(lo, hi)
        ax.set_title(' + '.join(names[m].split(' r=')[0] for m in drawn), fontsize=9)
        ax.set_xlabel('reduced dimension r', fontsize=8.5)
        ax.tick_params(labelsize=8)
        rs = [r for m in drawn for r in curves[m]['r']]
        if paper and method in paper:
            rs += list(paper[method]['r'])
        _r_ticks(ax, rs)
        if rs:
            ax.set_xlim(min(rs) - 1, max(rs) + 1)
        ax.grid(True, which='both', alpha=0.25)
    axes[0][0].set_ylabel(metric_label, fontsize=8.5)
    handles, entries = _errors_vs_r_legend(plt, curves, names, bool(paper), cut)
    return _finish(fig, path, title, handles, entries, ncol=4)


def _errors_vs_r_legend(plt: Any, curves: Mapping[str, Any], names: Mapping[str, str],
                        paper: bool, cut: int) -> tuple[list[Any], list[str]]:
    """Legend of :func:`errors_vs_r`: the two windows, the paper, one patch per method."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch
    handles: list[Any] = [Line2D([], [], ls=':', marker='o', color='0.2', ms=4.5),
                          Line2D([], [], ls='-.', marker='^', color='0.2', ms=4.5)]
    entries = ['training window', 'test window']
    if paper:
        handles.append(Line2D([], [], ls='-.', marker='^', color='0.65', ms=3))
        entries.append('the paper')
    for m in METHOD_ORDER:
        if m in curves:
            handles.append(Patch(color=COLORS[m]))
            entries.append(names[m])
    if cut:
        h, n = _off_handles(plt, cut)
        handles, entries = handles + h, entries + n
    return handles, entries


def output_traces(path: Path, t: NDArray[np.float64], fom: NDArray[np.float64],
                  roms: Mapping[str, NDArray[np.float64]], rows: Sequence[int],
                  row_names: Sequence[str], *, t_split: float | None = None,
                  rom_labels: Mapping[str, str] | None = None, scale: float = 1e3,
                  unit: str = 'mm', title: str = '', reference_label: str = 'FOM',
                  split_label: str = 'end of training') -> Path:
    """Paper Fig. 3: chosen outputs of the FOM (or measured data) and the ROMs against time.

    The axis range of each panel is the reference's range, widened by half of it on each
    side: a prediction that leaves it is cut at the edge and marked.

    Parameters
    ----------
    t : ndarray, shape (k,)
    fom : ndarray, shape (p, k)
        The reference outputs (FOM or measured), absolute, in the model's units.
    roms : dict
        ``key -> Ŷ (p, k)``; keys of :data:`COLORS` get the method's colour and style.
    rows : sequence of int
        Output indices to draw (one panel each).
    scale, unit : float, str
        Outputs are multiplied by ``scale`` and labelled in ``unit`` (default m → mm).
    t_split : float, optional
        End of training, a vertical magenta line (in the legend as ``split_label``).
    """
    plt = _plt()
    from matplotlib.ticker import ScalarFormatter
    fig, axes = plt.subplots(len(rows), 1, figsize=(WIDTH_IN, 1.0 + 2.0 * len(rows)),
                             sharex=True, squeeze=False)
    cut = 0
    for ax, row, name in zip(axes[:, 0], rows, row_names):
        ref = np.asarray(fom[row], dtype=np.float64) * scale
        lo, hi = float(np.min(ref)), float(np.max(ref))
        pad = max(hi - lo, 1e-9 * max(abs(hi), 1.0))
        lo, hi = lo - 0.5 * pad, hi + 0.5 * pad
        ax.plot(t, ref, color=COLORS['fom'], lw=2.0, label=reference_label)
        for i, (key, Y) in enumerate(roms.items()):
            label = (rom_labels or {}).get(key, LABELS.get(key, key))
            cut |= _plot_in_range(ax, t, np.asarray(Y[row]) * scale, lo, hi,
                                  ls=STYLES.get(key, '--'), color=COLORS.get(key, f'C{i + 1}'),
                                  lw=1.6, label=label)
        if t_split is not None:
            ax.axvline(t_split, color='magenta', lw=1.5, label=f'{split_label} '
                       f'(t = {t_split:g} s)')
        ax.set_ylim(lo, hi)
        fmt = ScalarFormatter(useOffset=False)
        ax.yaxis.set_major_formatter(fmt)
        ax.set_ylabel(f'{name} [{unit}]' if unit else name, fontsize=8.5)
        ax.tick_params(labelsize=8)
        ax.grid(True, alpha=0.3)
    axes[-1, 0].set_xlabel('time [s]', fontsize=8.5)
    handles, labels = _legend_entries(axes[:, 0])
    if cut:
        h, n = _off_handles(plt, cut)
        handles, labels = handles + h, labels + n
    return _finish(fig, path, title, handles, labels, ncol=min(len(labels), 4))


def error_bars(path: Path, errors: Mapping[str, Mapping[str, float]], *,
               paper: Mapping[str, Mapping[str, float]] | None = None,
               rom_labels: Mapping[str, str] | None = None,
               metric_label: str = 'Relative output error', title: str = '',
               y_max: float | None = None) -> Path:
    """Paper Fig. 4: bar chart of test errors per episode and method.

    Parameters
    ----------
    errors : dict
        ``method -> {episode -> error}``.
    paper : dict, optional
        The paper's errors, drawn as black ticks over the bars.
    y_max : float, optional
        Top of the axis: a taller bar is cut there, marked, and its value written on it.
    """
    plt = _plt()
    methods = [m for m in METHOD_ORDER if m in errors]
    episodes = list(next(iter(errors.values())).keys())
    x = np.arange(len(episodes))
    width = 0.8 / len(methods)
    fig, ax = plt.subplots(figsize=(WIDTH_IN, 3.4))
    vals_all = [errors[m][e] for m in methods for e in episodes if np.isfinite(errors[m][e])]
    top = max(vals_all + [v for m in methods for v in (paper or {}).get(m, {}).values()],
              default=1.0) * 1.08
    if y_max is not None:
        top = min(top, y_max)
    cut = 0
    for i, method in enumerate(methods):
        xs = x + (i - (len(methods) - 1) / 2) * width
        vals = np.array([errors[method][ep] for ep in episodes], dtype=np.float64)
        label = (rom_labels or {}).get(method, LABELS[method])
        over = ~np.isfinite(vals) | (vals > top)
        ax.bar(xs, np.where(over, top, vals), width, color=COLORS[method], label=label)
        for xo, v in zip(xs[over], vals[over]):
            cut |= ABOVE
            ax.plot([xo], [top], marker='^', color=COLORS[method], **_OFF)
            ax.text(xo, top * 0.97, f'{v:.3g}', rotation=90, ha='center', va='top',
                    fontsize=7, color='white')
        if paper and method in paper:
            pv = [paper[method].get(ep, np.nan) for ep in episodes]
            ax.plot(xs, pv, 'k_', ms=14, mew=2, label='paper')
    ax.set_ylim(0, top)
    ax.set_xticks(x)
    ax.set_xticklabels([ep.replace('ep', 'Ep ') for ep in episodes])
    ax.set_ylabel(metric_label, fontsize=8.5)
    ax.set_xlabel('test episode', fontsize=8.5)
    ax.tick_params(labelsize=8)
    ax.grid(True, axis='y', alpha=0.3)
    handles, labels = _legend_entries([ax])
    if cut:
        h, n = _off_handles(plt, cut)
        handles, labels = handles + h, labels + n
    return _finish(fig, path, title, handles, labels, ncol=min(len(labels), 5))


def centerline_shapes(path: Path, times: Sequence[float],
                      shapes: Mapping[str, Sequence[tuple[NDArray[np.float64],
                                                          NDArray[np.float64]]]], *,
                      rom_labels: Mapping[str, str] | None = None, scale: float = 1e3,
                      title: str = '') -> Path:
    """Paper Fig. 5: centerline x–z shapes (mm) of the FOM and the ROMs at given times.

    The z range of every panel is twice the FOM's largest deflection at any of the times
    (the same for all panels); a ROM shape that leaves it is cut at the edge and marked.

    Parameters
    ----------
    times : sequence of float
        One panel per time.
    shapes : dict
        ``'fom' | method -> [(x (N,), z (N,)) per time]`` in metres.
    """
    plt = _plt()
    fig, axes = plt.subplots(len(times), 1, figsize=(WIDTH_IN, 1.0 + 2.0 * len(times)),
                             sharex=True, squeeze=False)
    markers = {'fom': '^', 'lopinf': 'o', 'dmdc': '*', 'era': '+', 'lopinf_cubic': 's'}
    fz_all = [np.asarray(z) * scale for _x, z in shapes.get('fom', [])]
    zpad = max([float(np.max(np.abs(z))) for z in fz_all] + [5e-3 * scale])
    lo, hi = -2.0 * zpad, 2.0 * zpad
    cut = 0
    for i, (ax, tt) in enumerate(zip(axes[:, 0], times)):
        for key, per_time in shapes.items():
            x, z = (np.asarray(a, dtype=np.float64) * scale for a in per_time[i])
            label = (rom_labels or {}).get(key, LABELS.get(key, key))
            style: dict[str, Any] = dict(color=COLORS.get(key), lw=2.0 if key == 'fom' else 1.4,
                         ls='-' if key == 'fom' else STYLES.get(key, '--'), label=label)
            cut |= _plot_in_range(ax, x, z, lo, hi, **style)
            inside = (z >= lo) & (z <= hi)
            ax.plot(x[inside], z[inside], markers.get(key, '.'), color=COLORS.get(key), ms=3.5)
        ax.set_ylim(lo, hi)
        fx = np.asarray(shapes['fom'][i][0]) * scale if 'fom' in shapes else np.zeros(1)
        ax.set_xlim(float(np.min(fx)) - 0.03 * np.ptp(fx) - 1,
                    float(np.max(fx)) + 0.03 * np.ptp(fx) + 1)
        ax.text(0.01, 0.95, f't = {tt:g} s', transform=ax.transAxes, va='top', fontsize=8.5,
                bbox=dict(facecolor='white', edgecolor='none', alpha=0.8, pad=1.5))
        ax.set_ylabel('z [mm]', fontsize=8.5)
        ax.tick_params(labelsize=8)
        ax.grid(True, alpha=0.3)
    axes[-1, 0].set_xlabel('x [mm]', fontsize=8.5)
    handles, labels = _legend_entries(axes[:, 0])
    if cut:
        h, n = _off_handles(plt, cut)
        handles, labels = handles + h, labels + n
    return _finish(fig, path, title, handles, labels, ncol=min(len(labels), 3))
