"""The one registry of learners: method name -> learner class.

Every learner class has the same contract: hyperparameters in ``__init__``; ``reduction``,
what it needs from a reducer (``'pod'``, ``'identity'`` or ``'none'``, see
:data:`soft_rom.reduce.BASES`); ``coordinates_needed(r_max, n_inputs)``; ``fit(data) -> self``
on :class:`~soft_rom.reduce.ReducedData`; ``model_for(r)`` for another order from the same
fit; and the fitted ``model_``.
"""

from __future__ import annotations

from typing import Any, ClassVar, Protocol

from soft_rom.errors import ConfigError
from soft_rom.learners.dmdc import DMDc
from soft_rom.learners.era import ERAOKID
from soft_rom.learners.lopinf import LOpInf
from soft_rom.models import LinearROM
from soft_rom.reduce import ReducedData

__all__ = ['LEARNERS', 'Learner', 'learner_class']


class Learner(Protocol):
    """What the pipeline needs from a learner."""

    method: ClassVar[str]
    reduction: ClassVar[str]
    r: Any
    model_: Any

    def coordinates_needed(self, r_max: int | None, n_inputs: int) -> int | None:
        """Coordinates a reducer must keep for models up to ``r_max``."""
        ...

    def fit(self, data: ReducedData) -> Any:
        """Fit on reduced data; returns the learner."""
        ...

    def model_for(self, r: int) -> LinearROM:
        """The model of order ``r`` from the same fit."""
        ...


#: Method name (``soft-rom fit --method``) -> learner class.
LEARNERS: dict[str, type[Any]] = {'lopinf': LOpInf, 'dmdc': DMDc, 'era': ERAOKID}


def learner_class(method: str) -> type[Any]:
    """The learner class of ``method``."""
    try:
        return LEARNERS[method]
    except KeyError:
        raise ConfigError(f'--method must be one of {", ".join(LEARNERS)}; got '
                          f'{method!r}.') from None
