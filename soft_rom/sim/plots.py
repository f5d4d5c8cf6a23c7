"""Figures of simulated episodes (matplotlib, headless ``Agg`` backend)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from soft_rom.errors import ConfigError

__all__ = ['plot_centerline_shapes']


def plot_centerline_shapes(t: NDArray[np.float64], centerline: NDArray[np.float64],
                           times: Sequence[float], path: str | Path, *,
                           title: str = '') -> Path:
    """Save the centerline shapes (``z`` against ``x``, in mm) at chosen times as a PNG.

    Parameters
    ----------
    t : ndarray, shape (k,)
        Sample times (s).
    centerline : ndarray, shape (N, 3, k)
        Centerline points (m).
    times : sequence of float
        Times (s) to draw; each uses the nearest sample (the rest shape is drawn too).
    path : str or Path
        Output PNG file.

    Returns
    -------
    Path
    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    t = np.asarray(t, dtype=np.float64)
    if centerline.ndim != 3 or centerline.shape[1] != 3 or centerline.shape[2] != t.size:
        raise ConfigError(f'centerline must be (N, 3, {t.size}); got {centerline.shape}.')
    fig, ax = plt.subplots(figsize=(9, 3.6))
    ax.plot(1e3 * centerline[:, 0, 0], 1e3 * centerline[:, 2, 0], color='0.6', lw=1.5,
            ls='--', label=f't = {t[0]:.3f} s (rest)')
    for tq in times:
        j = int(np.argmin(np.abs(t - tq)))
        ax.plot(1e3 * centerline[:, 0, j], 1e3 * centerline[:, 2, j], marker='o', ms=3.5,
                lw=2, label=f't = {t[j]:.3f} s')
    ax.set_xlabel('x-coordinate [mm]')
    ax.set_ylabel('z-coordinate [mm]')
    ax.set_xlim(-20, 1220)
    ax.grid(True)
    ax.legend(loc='lower left', fontsize=8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
