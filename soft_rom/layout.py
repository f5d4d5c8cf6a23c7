"""The output layout: which centerline points and components form ``y``, in which order.

The converter knows it (from the mapping and the bag); it is stored as data in the
training set (root attribute ``output_layout``) and carried into every model file fitted
from it (``metadata['output_layout']``), so replay and the study read it instead of
re-deriving it from a mapping or parsing output names. :meth:`OutputLayout.from_names`
reads the names of files written before the layout was stored.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
import re
from typing import Any

from soft_rom.errors import ConfigError, DatasetError

__all__ = ['COMPONENTS', 'ORDERS', 'OutputLayout', 'layout_of', 'replay_components']

#: Coordinates a centerline point has.
COMPONENTS = ('x', 'y', 'z')
#: ``component_major``: ``[x_1..x_N, z_1..z_N]``; ``point_major``: ``[x_1, z_1, x_2, ...]``.
ORDERS = ('component_major', 'point_major')

_NAME = re.compile(r'^([xyz])(\d+)$')


@dataclass(frozen=True)
class OutputLayout:
    """Output layout of ``y`` (``p = len(components) * len(points)`` entries).

    Parameters
    ----------
    components : tuple of str
        Coordinates per point, a subset of ``x, y, z`` in their order in ``y``.
    order : {'component_major', 'point_major'}
    points : tuple of int
        0-based indices of the centerline points, in their order in ``y``.
    """

    components: tuple[str, ...]
    order: str
    points: tuple[int, ...]

    def __post_init__(self) -> None:
        if (not self.components or any(c not in COMPONENTS for c in self.components)
                or len(set(self.components)) != len(self.components)):
            raise DatasetError(f'output layout components must be distinct x, y, z; got '
                               f'{list(self.components)}.')
        if self.order not in ORDERS:
            raise DatasetError(f'output layout order must be one of {ORDERS}; got '
                               f'{self.order!r}.')
        if any(isinstance(i, bool) or not isinstance(i, int) or i < 0 for i in self.points):
            raise DatasetError('output layout points must be non-negative integers.')

    @property
    def size(self) -> int:
        """Number of outputs ``p``."""
        return len(self.components) * len(self.points)

    @property
    def component_string(self) -> str:
        """The components as one string (``'xz'``), as the predictor's parameter spells them."""
        return ''.join(self.components)

    def names(self) -> list[str]:
        """Output names (``x1 .. xN, z1 .. zN`` for component-major ``xz``; 1-based points)."""
        return [f'{c}{i + 1}' for c, i in self.entries()]

    def entries(self) -> list[tuple[str, int]]:
        """``(component, point index)`` of each output, in the order of ``y``."""
        if self.order == 'component_major':
            return [(c, i) for c in self.components for i in self.points]
        return [(c, i) for i in self.points for c in self.components]

    def index(self) -> dict[tuple[str, int], int]:
        """Row of ``y`` holding each ``(component, point index)``."""
        return {entry: row for row, entry in enumerate(self.entries())}

    def describe(self) -> str:
        """``'xz, component-major, points 1..10'`` (1-based points), for messages."""
        pts = [i + 1 for i in self.points]
        span = (f'{pts[0]}..{pts[-1]}'
                if len(pts) > 2 and pts == list(range(pts[0], pts[-1] + 1))
                else ', '.join(map(str, pts)))
        return f'{self.component_string}, {self.order.replace("_", "-")}, points {span}'

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (stored in training sets and model metadata)."""
        return {'components': list(self.components), 'order': self.order,
                'points': list(self.points)}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> OutputLayout:
        """Inverse of :meth:`to_dict`; :class:`DatasetError` on a malformed record."""
        try:
            comps = tuple(str(c) for c in data['components'])
            points = tuple(data['points'])
            order = str(data['order'])
        except (KeyError, TypeError) as err:
            raise DatasetError(f'malformed output layout {data!r} ({err}).') from None
        return cls(comps, order, points)

    @classmethod
    def from_names(cls, names: Sequence[str]) -> OutputLayout | None:
        """The layout that output names like ``x1 .. xN, z1 .. zN`` spell, or ``None``."""
        parsed = [_NAME.match(str(n)) for n in names]
        if not parsed or not all(parsed):
            return None
        pairs = [(m.group(1), int(m.group(2)) - 1) for m in parsed if m is not None]
        comps = tuple(dict.fromkeys(c for c, _ in pairs))
        points = tuple(dict.fromkeys(i for _, i in pairs))
        if min(points) < 0:
            return None
        for order in ORDERS:
            layout = cls(comps, order, points)
            if layout.entries() == pairs:
                return layout
        return None


def layout_of(metadata: Mapping[str, Any] | None,
              names: Sequence[str] | None = None) -> OutputLayout | None:
    """The layout stored in ``metadata['output_layout']``, else the one ``names`` spell.

    Parameters
    ----------
    metadata : mapping, optional
        Training-set attributes or model metadata.
    names : sequence of str, optional
        Output names, read when no layout is stored (files from before it was).
    """
    stored = (metadata or {}).get('output_layout')
    if stored is not None:
        return OutputLayout.from_dict(stored)
    return None if names is None else OutputLayout.from_names(names)


def replay_components(model_layout: OutputLayout | None,
                      data_layout: OutputLayout | None) -> str | None:
    """The output components a replay publishes: the model's layout, else the data's.

    Parameters
    ----------
    model_layout : OutputLayout, optional
        From the model file's metadata (fitted from a training set that stored it).
    data_layout : OutputLayout, optional
        From the episode being replayed (the converter's).

    Returns
    -------
    str or None
        Components as one string (``'xz'``), ``None`` when neither layout is known.

    Raises
    ------
    ConfigError
        The layouts disagree, or the layout is not component-major (the published points
        are read component-major).
    """
    if model_layout is not None and data_layout is not None and model_layout != data_layout:
        raise ConfigError(f'the model outputs {model_layout.describe()} but the bag gives '
                          f'{data_layout.describe()}; convert it with the output mapping the '
                          'model was trained with.')
    layout = model_layout if model_layout is not None else data_layout
    if layout is None:
        return None
    if layout.order != 'component_major':
        raise ConfigError(f'replay needs a component-major output order; the layout is '
                          f'{layout.order!r}.')
    return layout.component_string
