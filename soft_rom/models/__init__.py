"""Frozen reduced-order models: step, simulate, discretize, save, load.

* :mod:`~soft_rom.models.base` -- :class:`LinearROM`, the interface every model implements;
* :mod:`~soft_rom.models.linear` -- :class:`SecondOrderModel` (LOpInf) and
  :class:`DiscreteModel` (DMDc, ERA/OKID);
* :mod:`~soft_rom.models.cubic` -- :class:`CubicSecondOrderModel` (LOpInf with a quartic
  potential) and :mod:`~soft_rom.models.tensors` (its symmetric tensors);
* :mod:`~soft_rom.models.files` and :mod:`~soft_rom.models.archive` -- the model file: a
  bounded reader that knows no model class (each class registers itself) and
  :func:`load_model`.

Importing this package registers the built-in classes, so :func:`load_model` reads their
files.
"""

from __future__ import annotations

from soft_rom.models.base import DiscreteSystem, LinearROM, load_model, run_states, TRUST_TOL
from soft_rom.models.cubic import CubicSecondOrderModel
from soft_rom.models.files import (
    file_sha256,
    FORMAT_NAME,
    FORMAT_VERSION,
    MAX_STATES,
    register_model_class,
)
from soft_rom.models.linear import DiscreteModel, SecondOrderModel

__all__ = [
    'CubicSecondOrderModel',
    'DiscreteModel',
    'DiscreteSystem',
    'FORMAT_NAME',
    'FORMAT_VERSION',
    'LinearROM',
    'MAX_STATES',
    'SecondOrderModel',
    'TRUST_TOL',
    'file_sha256',
    'load_model',
    'register_model_class',
    'run_states',
]
