"""The eel study's settings: what the studies (and ``--era-preset eel``) use.

One source of defaults: the learners' own defaults serve any data; these hand-tuned settings
are the eel study's, and the study, the CLI (``soft-rom fit --era-preset eel``) and the Python
API (``ERAOKID(**ERA_EEL_OPTIONS)``) read them from here.
"""

from __future__ import annotations

from typing import Any

__all__ = ['CUBIC_EEL_OPTIONS', 'ERA_EEL_OPTIONS', 'ERA_PRESETS']

#: ERA/OKID on the eel (1 kHz, 40 outputs, slow lightly damped modes): identify on the 4
#: leading output principal components and the excited input directions, at the full rate,
#: with a 36-step observer and 500 Markov parameters (0.5 s), plain least squares (no ridge,
#: no selection).
ERA_EEL_OPTIONS: dict[str, Any] = {'decimation': 1, 'output_rank': 4, 'observer_order': 36,
                                   'n_markov': 500, 'selection': 'none', 'refit': False,
                                   'output_scale_floor': 0.0}

#: Named ERA/OKID settings of ``soft-rom fit --era-preset``: ``'auto'`` the learner's
#: data-driven defaults, ``'eel'`` :data:`ERA_EEL_OPTIONS`.
ERA_PRESETS: dict[str, dict[str, Any]] = {'auto': {}, 'eel': ERA_EEL_OPTIONS}

#: Cubic LOpInf settings hand-tuned on the eel before the held-out selection (a stronger
#: quartic floor than the learner's default), for a study with fixed ``cubic_options``. The
#: study and ``soft-rom fit`` choose from :data:`soft_rom.pipeline.cubic.CUBIC_GRID` instead:
#: on held-out eel episodes this floor was worse than the learner's at every ``reg``
#: (``docs/methods_variants.md``).
CUBIC_EEL_OPTIONS: dict[str, Any] = {'reg': 1e-3, 'eps4': 1e-2}
