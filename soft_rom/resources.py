"""What this process may still use: memory (a check made before large work starts)."""

from __future__ import annotations

import math
import os
from pathlib import Path

from soft_rom.errors import ResourceError

__all__ = ['available_memory', 'check_memory']


def available_memory() -> float:
    """Bytes of memory this process may still use: MemAvailable, capped by a cgroup limit."""
    avail = math.inf
    try:
        with open('/proc/meminfo', encoding='ascii') as fh:
            for line in fh:
                if line.startswith('MemAvailable:'):
                    avail = float(line.split()[1]) * 1024
                    break
    except OSError:
        pass
    for limit_file, usage_file in (('/sys/fs/cgroup/memory.max', '/sys/fs/cgroup/memory.current'),
                                   ('/sys/fs/cgroup/memory/memory.limit_in_bytes',
                                    '/sys/fs/cgroup/memory/memory.usage_in_bytes')):
        try:
            limit_text = Path(limit_file).read_text().strip()
            if limit_text == 'max':
                continue
            limit = float(limit_text)
            if limit > 2**60:
                continue
            used = float(Path(usage_file).read_text().strip())
            avail = min(avail, max(limit - used, 0.0))
        except (OSError, ValueError):
            continue
    if not math.isfinite(avail):
        try:
            avail = float(os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_AVPHYS_PAGES'))
        except (ValueError, OSError):
            avail = math.inf
    return avail


def check_memory(nbytes: float, what: str, advice: str) -> None:
    """Refuse before it starts a computation that needs ``nbytes`` of memory it cannot have.

    Raises
    ------
    ResourceError
        ``nbytes`` exceeds 80 % of :func:`available_memory`.
    """
    avail = available_memory()
    if nbytes > 0.8 * avail:
        raise ResourceError(f'{what} needs about {nbytes / 2**30:.3g} GiB of memory; '
                            f'{avail / 2**30:.3g} GiB are available. {advice}')
