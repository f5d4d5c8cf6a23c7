"""What a model is, in words and in file names: method, variant, forces, order and step.

One labelling for every table, plot and file: ``LOpInf cubic r=4``, ``DMDc stable r=8``,
``ERA/OKID r=20 dt=5 ms``; file stems ``lopinf_cubic_r4``, ``dmdc-stable_r8``,
``era_r20_dt5ms``. The step is named only where it differs from the data's.
"""

from __future__ import annotations

from typing import Any

__all__ = ['METHOD_NAMES', 'model_kind', 'model_label', 'model_stem']

#: How each method is written in tables and plots.
METHOD_NAMES = {'lopinf': 'LOpInf', 'dmdc': 'DMDc', 'era': 'ERA/OKID'}


def model_kind(model: Any) -> dict[str, Any]:
    """``method``, ``variant`` (DMDc), ``forces`` (LOpInf), ``r`` (the basis size) and ``dt``."""
    meta = getattr(model, 'metadata', {}) or {}
    method = str(getattr(model, 'method', ''))
    r = int(model.r)
    variant = forces = None
    if method == 'dmdc':
        variant = str(meta.get('variant') or 'paper')
        basis_r = meta.get('r')
        if isinstance(basis_r, int) and not isinstance(basis_r, bool):
            r = basis_r                   # the stable variant has 2r + m states
    if method == 'lopinf':
        forces = 'cubic' if getattr(model, 'is_nonlinear', False) else 'linear'
    return {'method': method, 'variant': variant, 'forces': forces, 'r': r,
            'dt': float(model.dt)}


def _dt_text(dt: float) -> str:
    ms = dt * 1e3
    return f'{ms:g} ms' if ms >= 0.01 else f'{dt:g} s'


def model_label(model: Any, *, data_dt: float | None = None) -> str:
    """``'LOpInf cubic r=4'``, ``'DMDc stable r=8'``, ``'ERA/OKID r=20 dt=5 ms'``.

    The step is added when ``data_dt`` is given and the model's differs from it.
    """
    k = model_kind(model)
    words = [METHOD_NAMES.get(k['method'], k['method'])]
    if k['forces'] == 'cubic':
        words.append('cubic')
    if k['variant'] not in (None, 'paper'):
        words.append(str(k['variant']))
    words.append(f'r={k["r"]}')
    if data_dt is not None and abs(k['dt'] - data_dt) > 1e-9 * data_dt:
        words.append(f'dt={_dt_text(k["dt"])}')
    return ' '.join(words)


def model_stem(model: Any, *, data_dt: float | None = None) -> str:
    """File-name stem: ``'lopinf_r4'``, ``'lopinf_cubic_r4'``, ``'dmdc-stable_r8'``, ...

    ``_dt5ms`` is appended when ``data_dt`` is given and the model's step differs from it.
    """
    k = model_kind(model)
    name = k['method'] + ('_cubic' if k['forces'] == 'cubic' else '')
    if k['variant'] not in (None, 'paper'):
        name += f'-{k["variant"]}'
    stem = f'{name}_r{k["r"]}'
    if data_dt is not None and abs(k['dt'] - data_dt) > 1e-9 * data_dt:
        stem += '_dt' + _dt_text(k['dt']).replace(' ', '').replace('.', 'p')
    return stem
