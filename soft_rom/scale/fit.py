"""Former name of :mod:`soft_rom.scale.streaming`, kept importable for one release.

``soft_rom.fitting`` fits over ranges of ``r``, each learner has its own ``fit``, and the
streaming reduce-then-fit functions now live in :mod:`soft_rom.scale.streaming`. Import them
from there (or from :mod:`soft_rom.scale`); this module will be removed in the next release.
"""

from soft_rom.scale.streaming import (
    ColumnWindow,
    fit_reduced_model,
    fit_streaming,
    make_executor,
    open_training_data,
    reduce_streaming,
    ReducedData,
    TrainingData,
)

__all__ = [
    'ColumnWindow',
    'ReducedData',
    'TrainingData',
    'fit_reduced_model',
    'fit_streaming',
    'make_executor',
    'open_training_data',
    'reduce_streaming',
]
