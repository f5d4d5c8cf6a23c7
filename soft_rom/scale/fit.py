"""Former name of :mod:`soft_rom.scale.streaming`, kept importable for one release.

``soft_rom.fitting`` fits over ranges of ``r``, each learner has its own ``fit``, and the
streaming reduce-then-fit functions now live in :mod:`soft_rom.scale.streaming`. Import them
from there (or from :mod:`soft_rom.scale`); this module will be removed in the next release.
"""

from typing import Any

from soft_rom.scale import streaming as _streaming

__all__ = list(_streaming.__all__)


def __getattr__(name: str) -> Any:
    """The names of :mod:`soft_rom.scale.streaming`, under their former module."""
    if name in __all__:
        return getattr(_streaming, name)
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
