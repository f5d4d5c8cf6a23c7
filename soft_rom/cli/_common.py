"""Small helpers shared by the CLI verbs."""

from __future__ import annotations

import argparse

__all__ = ['parse_r_list']


def parse_r_list(text: str) -> tuple[int, ...]:
    """Parse ``'16'``, ``'4,8,16'`` or ``'2:22:2'`` (inclusive stop) into a tuple of ints."""
    try:
        if ':' in text:
            parts = [int(p) for p in text.split(':')]
            if len(parts) not in (2, 3):
                raise ValueError
            start, stop = parts[0], parts[1]
            step = parts[2] if len(parts) == 3 else 1
            values = tuple(range(start, stop + 1, step))
        else:
            values = tuple(int(p) for p in text.split(',') if p.strip())
    except ValueError as err:
        raise argparse.ArgumentTypeError(
            f'expected r as N, N,M,... or START:STOP[:STEP]; got {text!r}') from err
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f'r values must be positive integers; got {text!r}')
    return values
