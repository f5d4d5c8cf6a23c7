"""The closed-loop figure: shapes, error over time, pressures with their bounds."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

__all__ = ['closed_loop_figure']


def _xz(names: list[str], y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    xs = [i for i, n in enumerate(names) if n.startswith('x')]
    zs = [i for i, n in enumerate(names) if n.startswith('z')]
    return y[xs], y[zs]


def _below(ax: Any, ncol: int) -> None:
    """The panel's legend under its x label, where it covers no trace."""
    ax.legend(fontsize=8, ncol=ncol, loc='upper center', bbox_to_anchor=(0.5, -0.2),
              frameon=False)


def closed_loop_figure(path: str | Path, res: Any, output_names: list[str], *,
                       title: str = '', open_loop: np.ndarray | None = None) -> Path:
    """Write the figure of a :class:`~soft_rom.control.loop.ClosedLoopResult`.

    Top: reference (dashed) and achieved centerline (x, z in mm) at four times. Middle: the
    RMS output error over time (mm), and the open-loop one when given. Bottom: the
    pressures (kPa) with their bounds.
    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    path = Path(path)
    fig, axes = plt.subplots(3, 1, figsize=(8.0, 9.8), constrained_layout=True)
    t = res.t
    times = t[-1] * np.array([0.55, 0.7, 0.85, 1.0])   # not whole periods of a 2 Hz wave
    colors = plt.rcParams['axes.prop_cycle'].by_key()['color']
    ax = axes[0]
    for i, tt in enumerate(times):
        j = min(int(np.searchsorted(t, tt)), t.size - 1)
        xr, zr = _xz(output_names, res.Y_ref[:, j])
        xa, za = _xz(output_names, res.Y[:, j])
        c = colors[i % len(colors)]
        ax.plot(1e3 * xr, 1e3 * zr, '--', color=c, lw=1.2)
        ax.plot(1e3 * xa, 1e3 * za, '-', color=c, lw=1.8, label=f't = {t[j]:.2f} s')
    ax.plot([], [], 'k--', lw=1.2, label='reference')
    ax.plot([], [], 'k-', lw=1.8, label='achieved')
    ax.set_xlabel('x [mm]')
    ax.set_ylabel('z [mm]')
    ax.set_title('Centerline: reference (dashed) and achieved (solid)')
    _below(ax, ncol=6)
    ax.grid(alpha=0.3)
    ax = axes[1]
    p = res.Y.shape[0]
    ax.plot(t, 1e3 * np.linalg.norm(res.Y - res.Y_ref, axis=0) / np.sqrt(p), lw=1.2,
            label=f'closed loop (deviation error {res.tracking_error():.3f})')
    if open_loop is not None:
        ax.plot(t, 1e3 * np.linalg.norm(open_loop - res.Y_ref, axis=0) / np.sqrt(p), lw=1.0,
                alpha=0.8, label='open loop')
    ax.plot(t, 1e3 * np.linalg.norm(res.Y_ref - res.y_ref[:, None], axis=0) / np.sqrt(p),
            'k:', lw=1.0, label='reference deviation (scale)')
    ax.set_xlabel('t [s]')
    ax.set_ylabel('RMS over outputs [mm]')
    ax.set_title('Tracking error')
    _below(ax, ncol=3)
    ax.grid(alpha=0.3)
    ax = axes[2]
    for i in range(res.U.shape[0]):
        ax.plot(t, res.U[i] / 1e3, lw=1.0, color=colors[i % len(colors)], label=f'u{i + 1}')
    lo = np.broadcast_to(np.asarray(res.u_min, dtype=np.float64), (res.U.shape[0],))
    hi = np.broadcast_to(np.asarray(res.u_max, dtype=np.float64), (res.U.shape[0],))
    for i in range(res.U.shape[0]):           # each chamber's own bounds, in its colour
        c = colors[i % len(colors)]
        ax.hlines([lo[i] / 1e3, hi[i] / 1e3], t[0], t[-1], colors=c, lw=0.9, ls=(0, (4, 3)))
    ax.plot([], [], color='0.3', lw=0.9, ls=(0, (4, 3)), label='bounds')
    ax.set_xlabel('t [s]')
    ax.set_ylabel('pressure [kPa]')
    ax.set_title('Pressures applied (each with its bounds, dashed)')
    _below(ax, ncol=7)
    ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
