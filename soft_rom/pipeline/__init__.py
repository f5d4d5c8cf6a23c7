"""One pipeline from a training set to models: what ``soft-rom fit``, the API and the studies run.

* :mod:`~soft_rom.pipeline.data` -- the training episodes, references and coordinates;
* :mod:`~soft_rom.pipeline.fit` -- :func:`fit_models`: reduce once, fit a learner, one model
  per ``r``, each model's metadata finalized in one place (:func:`finalize_model`);
* :mod:`~soft_rom.pipeline.settings` -- :class:`FitSettings`, the defaults of every choice,
  and :func:`fit_method`, one method as ``soft-rom fit`` fits it;
* :mod:`~soft_rom.pipeline.cubic` -- the one held-out selection of the cubic LOpInf: its
  settings, and whether it beats the linear model (:class:`HeldOutCubicSelection`), used by
  ``soft-rom fit --forces cubic|auto`` and the studies.

>>> data = open_training_data('eel.zarr', episodes='ep1,ep2')         # doctest: +SKIP
>>> fitted = fit_method(data, 'lopinf', (4, 8))                      # doctest: +SKIP
>>> fitted = fit_models(data, LOpInf(), (4, 8), StreamingReducer())  # doctest: +SKIP
"""

from __future__ import annotations

from soft_rom.pipeline.cubic import CUBIC_GRID, CubicVerdict, folds_of, HeldOutCubicSelection
from soft_rom.pipeline.data import (
    choose_coordinates,
    COORDINATES,
    open_training_data,
    output_coordinates,
    select_episodes,
)
from soft_rom.pipeline.fit import (
    finalize_model,
    fit_models,
    FittedModel,
    for_orders,
    held_out_by_order,
    Reducer,
)
from soft_rom.pipeline.settings import fit_method, FitSettings, make_learner, replace_learner

__all__ = ['COORDINATES', 'CUBIC_GRID', 'CubicVerdict', 'FitSettings', 'FittedModel',
           'HeldOutCubicSelection', 'Reducer', 'choose_coordinates', 'finalize_model',
           'fit_method', 'fit_models', 'folds_of', 'for_orders', 'held_out_by_order',
           'make_learner', 'open_training_data', 'output_coordinates', 'replace_learner',
           'select_episodes']
