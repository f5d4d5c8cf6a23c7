"""Dask worker preload of the fault tests: every block read sleeps first.

``SOFT_ROM_TEST_READ_DELAY`` seconds (default 0) before each read of a training-set array, so
that a pass lasts long enough to kill a worker or the scheduler in the middle of it. The
worker may import a preload more than once: the read is wrapped once.
"""

import os
import time

from soft_rom.dataset import stored

_DELAY = float(os.environ.get('SOFT_ROM_TEST_READ_DELAY', '0'))

if _DELAY > 0 and not hasattr(stored.StoredArray, '_unslowed_getitem'):
    stored.StoredArray._unslowed_getitem = stored.StoredArray.__getitem__

    def _slow_read(self, key):
        time.sleep(_DELAY)
        return stored.StoredArray._unslowed_getitem(self, key)

    stored.StoredArray.__getitem__ = _slow_read
