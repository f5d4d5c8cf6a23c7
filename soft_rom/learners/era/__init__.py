"""ERA/OKID: linear ROMs from the inputs and outputs of one episode (paper section 2.4).

* :mod:`~soft_rom.learners.era.okid` -- OKID Markov parameters and data preparation;
* :mod:`~soft_rom.learners.era.realization` -- ERA realizations, stabilization, resampling;
* :mod:`~soft_rom.learners.era.select` -- settings chosen by blocked cross-validation;
* :mod:`~soft_rom.learners.era.learner` -- :class:`ERAOKID`, the learner.
"""

from __future__ import annotations

from soft_rom.learners.era.learner import ERAOKID
from soft_rom.learners.era.okid import decimate, okid_markov
from soft_rom.learners.era.realization import check_hankel_memory, era, hankel_rank

__all__ = ['ERAOKID', 'check_hankel_memory', 'decimate', 'era', 'hankel_rank', 'okid_markov']
