"""Envelopes: the range of inputs a model was trained on, and the bound of a sane output.

:func:`training_envelope` is called where model metadata is assembled at fit time; it
records, per input channel, the smallest and largest training value and, for the outputs,
the largest deviation from the reference ``max |Y - y_ref|``:

.. code-block:: python

    {'u_min': [...], 'u_max': [...], 'y_dev_max': float, 'samples': int}

stored as ``model.metadata['envelope']``. :class:`Envelopes` turns it (and the
predictor's settings) into the bounds the predictor applies:

* input envelope -- ``[lo - f w, hi + f w]`` per channel with ``w = hi - lo`` and
  ``f = input_envelope_margin`` (default 1); an explicit ``input_min`` / ``input_max``
  (one value per input, or one for all) replaces its side, the other side staying as it
  is; a model file without a recorded range has none (only the configured side bounds);
* output envelope -- ``max |y_hat - y_ref| <= output_envelope_factor * S`` with ``S`` the
  recorded ``y_dev_max`` (files without it: ``max |y_ref|``, or 1 if that is 0).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from soft_rom.data import all_finite
from soft_rom.envelope import check_bound_units, training_envelope
from soft_rom.errors import ConfigError

__all__ = ['Envelopes', 'training_envelope']

Array = NDArray[np.float64]


class Envelopes:
    """Input and output bounds of one model under one configuration.

    Parameters
    ----------
    model : object
        With ``n_inputs``, ``y_ref`` and ``metadata``.
    config : PredictorConfig

    Attributes
    ----------
    u_lo, u_hi : ndarray, shape (m,) or None
        Input envelope (``None``: none; ``-inf`` / ``inf``: no bound on that side).
    y_bound : float
        Largest allowed ``max |y - y_ref|``.
    input_source, output_source : str
        Where the bounds came from, for the health values and the docs.
    """

    def __init__(self, model: Any, config: Any) -> None:
        m = int(model.n_inputs)
        meta = model.metadata.get('envelope') if isinstance(model.metadata, dict) else None
        meta = meta if isinstance(meta, dict) else {}
        self.u_lo: Array | None = None
        self.u_hi: Array | None = None
        self.input_source = 'none'
        lo_cfg = _configured(config.input_min, m, 'input_min')
        hi_cfg = _configured(config.input_max, m, 'input_max')
        lo, hi = _floats(meta.get('u_min'), m), _floats(meta.get('u_max'), m)
        train_lo = train_hi = None
        trained = 'none recorded in the model file'
        if lo is not None and hi is not None and np.all(lo <= hi):
            width = hi - lo
            f = float(config.input_envelope_margin)
            train_lo, train_hi = lo - f * width, hi + f * width
            trained = f'training range widened by {f:g} x its width'
        if lo_cfg is None and hi_cfg is None:
            if train_lo is not None:
                self.u_lo, self.u_hi = train_lo, train_hi
                self.input_source = trained
        else:
            self.u_lo = lo_cfg if lo_cfg is not None else (
                train_lo if train_lo is not None else np.full(m, -np.inf))
            self.u_hi = hi_cfg if hi_cfg is not None else (
                train_hi if train_hi is not None else np.full(m, np.inf))
            if lo_cfg is not None and hi_cfg is not None:
                self.input_source = 'configured'
            elif lo_cfg is not None:
                self.input_source = f'input_min configured; input_max: {trained}'
            else:
                self.input_source = f'input_max configured; input_min: {trained}'
            bad = np.flatnonzero(self.u_lo > self.u_hi)
            if bad.size:
                i = int(bad[0])
                names = list(getattr(model, 'input_names', ()) or ())
                name = names[i] if i < len(names) else str(i + 1)
                raise ConfigError(
                    f'input_min must not exceed input_max: input {name} would get '
                    f'{self.u_lo[i]:g} > {self.u_hi[i]:g} (input envelope: '
                    f'{self.input_source}).')
            if lo_cfg is not None and hi_cfg is not None and train_lo is not None:
                check_bound_units(model, lo_cfg, hi_cfg, lo, hi, 'input_min/input_max')
        y_ref = np.asarray(model.y_ref, dtype=np.float64)
        dev = meta.get('y_dev_max')
        if isinstance(dev, (int, float)) and math.isfinite(dev) and dev > 0:
            scale = float(dev)
            self.output_source = 'training max |Y - y_ref|'
        else:
            scale = float(np.max(np.abs(y_ref))) if y_ref.size else 0.0
            if not (math.isfinite(scale) and scale > 0):
                scale = 1.0
            self.output_source = 'max |y_ref| (no training envelope in the model file)'
        self.y_scale = scale
        self.y_bound = float(config.output_envelope_factor) * scale

    def input_ok(self, index: int, value: float) -> bool:
        """Whether one channel's value is inside the input envelope."""
        if self.u_lo is None or self.u_hi is None:
            return True
        return bool(self.u_lo[index] <= value <= self.u_hi[index])

    def clip(self, index: int, value: float) -> float:
        """``value`` clipped into channel ``index``'s envelope."""
        if self.u_lo is None or self.u_hi is None:
            return value
        return float(min(max(value, self.u_lo[index]), self.u_hi[index]))

    def output_ok(self, dev_inf: float) -> bool:
        """Whether ``max |y - y_ref|`` (``dev_inf``) is inside the output envelope."""
        return dev_inf <= self.y_bound      # False for NaN

    def summary(self) -> dict[str, Any]:
        """JSON-able description (for ``model_info`` and diagnostics)."""
        return {
            'input_min': _side(self.u_lo),
            'input_max': _side(self.u_hi),
            'input_source': self.input_source,
            'output_bound': self.y_bound,
            'output_source': self.output_source,
        }


def _side(bound: Array | None) -> list[float] | None:
    """One side of the input envelope for JSON: ``None`` where it does not bound."""
    if bound is None or not np.any(np.isfinite(bound)):
        return None
    return [float(v) for v in bound]


def _configured(values: tuple[float, ...], m: int, name: str) -> Array | None:
    """A configured bound for ``m`` inputs (one value: every input); ``None``: not set."""
    if not values:
        return None
    if len(values) not in (1, m):
        raise ConfigError(f'{name} lists {len(values)} values; the model has {m} inputs '
                          f'(give one value per input, or one for all).')
    return np.broadcast_to(np.array(values, dtype=np.float64), (m,)).copy()


def _floats(values: Any, m: int) -> Array | None:
    if not isinstance(values, list) or len(values) != m:
        return None
    try:
        arr = np.array([float(v) for v in values], dtype=np.float64)
    except (TypeError, ValueError):
        return None
    return arr if all_finite(arr) else None
