"""The range of the training data, recorded in a model file at fit time.

:func:`training_envelope` is called where model metadata is assembled (the learners'
``fit``, the streaming fit); the predictor derives its default input envelope and its
divergence bound from the result (:mod:`soft_rom.predictor.envelope`).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.errors import ConfigError

__all__ = ['check_bound_units', 'training_envelope']

Array = NDArray[np.float64]


#: Share of the training outputs' motion (deviation power) below ``y_band_hz``.
BAND_SHARE = 0.99


def training_envelope(episodes: Iterable[Any], y_ref: ArrayLike | None = None,
                      dt: float | None = None) -> dict[str, Any]:
    """Range of the training data, for the model file's ``metadata['envelope']``.

    Parameters
    ----------
    episodes : iterable
        Objects with ``U`` (m, k) and ``Y`` (p, k) attributes (:class:`~soft_rom.data.Episode`),
        or ``(U, Y)`` pairs.
    y_ref : ndarray, shape (p,), optional
        Output reference; default the first output sample of the first episode.
    dt : float, optional
        Sample time (s) of the episodes; with it, ``y_band_hz`` is recorded.

    Returns
    -------
    dict
        ``u_min``, ``u_max`` (lists of m floats), ``y_dev_max`` (float, ``max |Y - y_ref|``
        over all outputs and samples; ``None`` without outputs) and ``samples``; with ``dt``
        also ``y_band_hz``: the frequency below which :data:`BAND_SHARE` of the outputs'
        motion lies (the power of ``Y`` less its mean, summed over outputs; the largest over
        episodes of 16 samples or more; ``None`` where none moves). A reference faster
        than that asks the model where its training data did not go.
    """
    lo: Array | None = None
    hi: Array | None = None
    dev = 0.0
    have_y = False
    samples = 0
    band: float | None = None
    ref = None if y_ref is None else np.asarray(y_ref, dtype=np.float64).reshape(-1)
    for ep in episodes:
        U, Y = (ep.U, ep.Y) if hasattr(ep, 'U') else ep
        U = np.asarray(U, dtype=np.float64)
        Y = np.asarray(Y, dtype=np.float64)
        if U.ndim == 2 and U.shape[1]:
            u_lo, u_hi = np.nanmin(U, axis=1), np.nanmax(U, axis=1)
            lo = u_lo if lo is None else np.minimum(lo, u_lo)
            hi = u_hi if hi is None else np.maximum(hi, u_hi)
            samples += U.shape[1]
        if Y.ndim == 2 and Y.shape[0] and Y.shape[1]:
            if ref is None:
                ref = Y[:, 0].copy()
            if ref.shape[0] == Y.shape[0]:
                dev = max(dev, float(np.nanmax(np.abs(Y - ref[:, None]))))
                have_y = True
            f = _band(Y, dt) if dt is not None else None
            band = f if band is None or (f is not None and f > band) else band
    return {
        'u_min': [] if lo is None else [float(v) for v in lo],
        'u_max': [] if hi is None else [float(v) for v in hi],
        'y_dev_max': dev if have_y else None,
        'samples': int(samples),
        **({} if dt is None else {'y_band_hz': band}),
    }


def _band(Y: Array, dt: float) -> float | None:
    """The frequency (Hz) below which :data:`BAND_SHARE` of ``Y``'s motion lies, or None."""
    if Y.shape[1] < 16 or not (dt > 0) or not np.all(np.isfinite(Y)):
        return None
    power = np.sum(np.abs(np.fft.rfft(Y - Y.mean(axis=1, keepdims=True), axis=1)) ** 2,
                   axis=0)
    total = float(np.sum(power))
    if not total > 0:
        return None
    at = int(np.searchsorted(np.cumsum(power), BAND_SHARE * total))
    return float(np.fft.rfftfreq(Y.shape[1], dt)[min(at, power.size - 1)])


def check_bound_units(model: Any, lo: Array, hi: Array, t_lo: Any, t_hi: Any,
                      what: str) -> None:
    """Refuse bounds ``[lo, hi]`` 1000 x narrower or wider than the training range (units?).

    The predictor's input envelope and the MPC's input bounds (``what`` names them in the
    message): kPa given to a model in Pa would clip every input to a thousandth of its range.
    """
    t_lo, t_hi = np.asarray(t_lo, dtype=np.float64), np.asarray(t_hi, dtype=np.float64)
    trained = float(np.max(t_hi - t_lo))
    given = float(np.max(hi - lo))
    if trained > 0 and not 1e-3 <= given / trained <= 1e3:
        units = sorted({u for u in getattr(model, 'input_units', None) or () if u}) or [
            'unnamed in the model file']
        raise ConfigError(f'{what} [{float(np.min(lo)):g}, {float(np.max(hi)):g}] span '
                          f'{given / trained:.2g} x the training range [{float(np.min(t_lo)):g},'
                          f" {float(np.max(t_hi)):g}]: give them in the model's input units "
                          f'({", ".join(units)}).')
