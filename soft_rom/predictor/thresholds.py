"""Monitor thresholds: multiples of the model's own held-out error unless set by hand.

A model file records at fit time how well its fit predicts data it did not see
(``model.metadata['held_out']``):

.. code-block:: python

    {'deviation_error': float, 'absolute_error': float, 'data': str}

the relative output error on deviations from ``y_ref`` and on absolute outputs, and which
data was held out. :class:`Thresholds` turns it into the thresholds the health check uses
for the windowed error of the chosen ``error_metric``:

* ``warn_threshold = 0`` (the default): :data:`WARN_FACTOR` times the held-out error;
* ``error_threshold = 0`` (the default): :data:`ERROR_FACTOR` times the held-out error;
* a positive value is used as it is; where only one is set, the other (from the model)
  is moved so that ``warn <= error`` holds;
* a model file without a held-out error (written before it was recorded) gets the
  former fixed defaults :data:`DEFAULT_WARN` and :data:`DEFAULT_ERROR`.

So the monitor says WARN when the model predicts markedly worse than it did on its own
held-out data -- inputs it was not trained for, a robot that changed -- and stays OK for
a model doing as well as it was shown to.
"""

from __future__ import annotations

import math
from typing import Any

__all__ = ['DEFAULT_ERROR', 'DEFAULT_WARN', 'ERROR_FACTOR', 'held_out_error', 'Thresholds',
           'WARN_FACTOR']

#: Warn above this multiple of the held-out error.
WARN_FACTOR = 2.0
#: Error above this multiple of the held-out error.
ERROR_FACTOR = 4.0
#: Thresholds of model files without a held-out error.
DEFAULT_WARN = 0.1
DEFAULT_ERROR = 0.3


def held_out_error(model: Any, metric: str = 'deviation') -> float | None:
    """The held-out relative error recorded in ``model``'s metadata (``None``: none usable).

    ``metric`` is ``'deviation'`` or ``'absolute'`` (as ``error_metric``).
    """
    meta = getattr(model, 'metadata', None)
    held = meta.get('held_out') if isinstance(meta, dict) else None
    if not isinstance(held, dict):
        return None
    value = held.get('deviation_error' if metric == 'deviation' else 'absolute_error')
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    value = float(value)
    return value if math.isfinite(value) and value > 0 else None


class Thresholds:
    """The warn and error thresholds in force for one model and configuration.

    Parameters
    ----------
    model : object
        With ``metadata`` (a dict).
    config : PredictorConfig

    Attributes
    ----------
    warn, error : float
        Windowed relative error above which the health is WARN / ERROR.
    held_out : float or None
        The model's held-out error of the configured metric, when recorded.
    source : str
        Where the thresholds came from, in words (health values, ``model_info``).
    warn_why, error_why : str
        Said after a threshold in a health message: ``' (2 x the held-out error 0.16)'``
        when it is such a multiple, else empty.
    """

    def __init__(self, model: Any, config: Any) -> None:
        metric = str(config.error_metric)
        self.held_out = held_out_error(model, metric)
        if self.held_out is not None:
            auto_warn, auto_error = WARN_FACTOR * self.held_out, ERROR_FACTOR * self.held_out
            auto = (f'{WARN_FACTOR:g} x / {ERROR_FACTOR:g} x the held-out {metric} error '
                    f'{self.held_out:.3g} recorded in the model file')
        else:
            auto_warn, auto_error = DEFAULT_WARN, DEFAULT_ERROR
            auto = 'defaults (the model file records no held-out error)'
        warn, error = float(config.warn_threshold), float(config.error_threshold)
        self.warn, self.error = warn if warn > 0 else auto_warn, error if error > 0 else auto_error
        if warn > 0 and error <= 0:
            self.error = max(auto_error, warn)
        elif error > 0 and warn <= 0:
            self.warn = min(auto_warn, error)
        self.source = {(True, True): 'set', (True, False): f'warn set, error from {auto}',
                       (False, True): f'error set, warn from {auto}',
                       (False, False): auto}[(warn > 0, error > 0)]

        def why(value: float, factor: float, configured: float) -> str:
            if configured > 0 or self.held_out is None or value != factor * self.held_out:
                return ''
            return f' ({factor:g} x the held-out error {self.held_out:.3g})'

        self.warn_why = why(self.warn, WARN_FACTOR, warn)
        self.error_why = why(self.error, ERROR_FACTOR, error)

    def summary(self) -> dict[str, Any]:
        """JSON-able description (``model_info``, health values)."""
        return {'warn_threshold': self.warn, 'error_threshold': self.error,
                'held_out_error': self.held_out, 'threshold_source': self.source}
