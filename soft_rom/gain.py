"""Steady-state gain of a linear ROM against the range of its training data (a trust check).

A model can be stable, with symmetric positive stiffness and damping, and still be absurd:
``B`` a thousand times too large moves the robot by kilometres for the pressures it was
trained on. What the model predicts for an input held long enough is its steady state

.. math::

    y_\\infty - y_{ref} = G u, \\qquad G = C (I - A)^{-1} B + D
    \\quad (\\text{LOpInf: } G = E K^{-1} B),

and over the training input box ``u_min <= u <= u_max`` (recorded in the model file,
``metadata['envelope']``, see :mod:`soft_rom.envelope`) output ``i`` moves at most

.. math::

    g_i = \\max_{u_{min} \\le u \\le u_{max}} |G_i u|
        = \\max\\Big(\\sum_j \\max(G_{ij} u^{min}_j, G_{ij} u^{max}_j),\\;
                    -\\sum_j \\min(G_{ij} u^{min}_j, G_{ij} u^{max}_j)\\Big)

(a linear function on a box is largest at a corner, chosen per input by the sign of
``G_ij``). An input held no longer than the training data lasted (``samples`` steps) is what
the data can vouch for: a mode too slow to show in it (a stiffness the fit could hardly see)
may have a large steady state that no recording will reach, so linear models are judged on
the gains of inputs held for 1, 2, 4, ... steps up to that length (:func:`held_input_gains`),
whose limit is ``G``. :func:`gain_issue` compares ``max_i g_i`` with the largest deviation of the
training outputs ``S = max |Y - y_ref|``: beyond :data:`GAIN_FACTOR` ``S`` (100, the
predictor's default divergence bound ``output_envelope_factor``) the model is not trusted.
The steady state is the cheap and robust measure: one ``r x r`` solve, no frequency grid,
and it is what a pressure held for a while produces. Unstable models are left to the
stability check (their steady state is not reached); a singular ``I - A`` (a pure
integrator) is an infinite gain.
"""

from __future__ import annotations

from collections.abc import Mapping
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ['GAIN_FACTOR', 'box_response', 'equilibrium', 'gain_issue', 'held_input_gains',
           'peak_response', 'steady_state_gain']

Array = NDArray[np.float64]

#: A steady state beyond this multiple of the largest training output deviation is absurd.
GAIN_FACTOR = 100.0


def steady_state_gain(model: Any) -> Array:
    """Steady-state gain ``G`` (p, m) of a linear model: ``y_inf - y_ref = G u``.

    Parameters
    ----------
    model : LinearROM
        A second-order model (``K``, ``B``, ``E``: ``G = E K^{-1} B``, exact, without the
        discretization's rounding) or any model with a native discrete :attr:`system`
        (``G = C (I - A)^{-1} B + D``).

    Returns
    -------
    ndarray, shape (p, m)
        ``inf`` in every entry when the system matrix is singular (an integrator).
    """
    K, B, E = (getattr(model, name, None) for name in ('K', 'B', 'E'))
    if isinstance(K, np.ndarray) and isinstance(E, np.ndarray) and isinstance(B, np.ndarray):
        M, rhs, out, feed = K, B, E, None
    else:
        A, B, C, D, _ = model.system
        M, rhs, out, feed = np.eye(A.shape[0]) - A, B, C, D
    p, m = out.shape[0], rhs.shape[1]
    if M.size == 0:
        return np.zeros((p, m)) if feed is None else np.array(feed, dtype=np.float64)
    try:
        with np.errstate(all='ignore'):
            X = np.linalg.solve(M, rhs)
            cond = np.linalg.cond(M)
    except np.linalg.LinAlgError:
        return np.full((p, m), np.inf)
    if not math.isfinite(cond) or cond > 1.0 / np.finfo(np.float64).eps:
        return np.full((p, m), np.inf)
    with np.errstate(all='ignore'):
        G = out @ X
        if feed is not None:
            G = G + feed
    return np.asarray(G, dtype=np.float64)


def box_response(G: Array, u_min: Array, u_max: Array) -> Array:
    """Largest ``|G_i u|`` per output over the box ``u_min <= u <= u_max``; shape (p,)."""
    with np.errstate(all='ignore'):
        lo, hi = G * u_min[None, :], G * u_max[None, :]
        top = np.where(np.isnan(lo) | np.isnan(hi), np.inf, np.maximum(lo, hi)).sum(axis=1)
        bottom = np.where(np.isnan(lo) | np.isnan(hi), -np.inf, np.minimum(lo, hi)).sum(axis=1)
    return np.maximum(np.abs(top), np.abs(bottom))


def equilibrium(model: Any, force: Array, iterations: int = 200) -> Array:
    """The rest position ``q`` of a model with a potential: ``∇V(q) = force``, shape (r,).

    Damped Newton on ``V(q) - forceᵀ q`` (the tangent stiffness where it is positive
    definite, else the gradient; backtracking), from the rest position ``q = 0``: for the
    cubic LOpInf model, whose trust check certifies that the quartic part of ``V`` is
    positive, that function is bounded below and the minimum is the steady state.
    """
    q = np.zeros(model.r)
    scale = max(1.0, float(np.linalg.norm(force)))

    def energy(x: Array) -> float:
        return float(model.potential(x) - force @ x)

    for _ in range(iterations):
        g = model.force(q) - force
        if not np.all(np.isfinite(g)):
            return np.full(model.r, np.inf)
        if float(np.linalg.norm(g)) <= 1e-10 * scale:
            break
        try:
            d = -np.linalg.solve(model.stiffness(q), g)
            if not float(g @ d) < 0:
                d = -g
        except np.linalg.LinAlgError:
            d = -g
        e0, slope, t = energy(q), float(g @ d), 1.0
        while t > 1e-14 and not energy(q + t * d) <= e0 + 1e-4 * t * slope:
            t *= 0.5
        q = q + t * d
    return q


def held_input_gains(model: Any, horizon: int) -> list[Array]:
    """Gains ``G_k`` (p, m) of inputs held for ``k = 1, 2, 4, ...`` steps up to ``horizon``.

    ``G_k = C Σ_{i<k} A^i B + D``: the response from rest is ``y_k - y_ref = G_k u``.
    Doubling (``Σ_2k = Σ_k + A^k Σ_k``): about ``log2(horizon)`` products of ``r x r``.
    """
    A, B, C, D, _ = model.system
    sigma, power, k = np.array(B, dtype=np.float64), np.array(A, dtype=np.float64), 1
    out = []
    with np.errstate(all='ignore'):
        while True:
            out.append(C @ sigma + D)
            if k >= horizon:
                return out
            sigma = sigma + power @ sigma
            power = power @ power
            k *= 2


def peak_response(model: Any, u_min: Array, u_max: Array, horizon: int | None = None
                  ) -> Array:
    """Largest ``|y_i - y_ref_i|`` for inputs held within the box, per output; shape (p,).

    Linear models: :func:`box_response` of the gains of inputs held for up to ``horizon``
    steps (:func:`held_input_gains`; default: for ever, the steady state) -- a mode so slow
    that the training data could not see it does not count beyond the training length. A
    model with a
    potential (``force``, ``stiffness``, ``potential``: the cubic LOpInf) is solved at the
    corners that are the worst for its linearization (two per output) with
    :func:`equilibrium`: its stiffness grows with the displacement, so its linear part
    alone would overstate the gain.
    """
    linear = model.linear_part() if hasattr(model, 'linear_part') else model
    G = steady_state_gain(linear)
    if not all(hasattr(model, name) for name in ('force', 'stiffness', 'potential')):
        if horizon is None:
            return box_response(G, u_min, u_max)
        peaks = [box_response(Gk, u_min, u_max) for Gk in held_input_gains(model, horizon)]
        return np.max(np.array(peaks), axis=0)
    corners = {tuple(np.where(G[i] * sign > 0, u_max, u_min)) for i in range(G.shape[0])
               for sign in (1.0, -1.0)}
    peak = np.zeros(G.shape[0])
    for corner in corners:
        q = equilibrium(model, model.B @ np.array(corner))
        with np.errstate(all='ignore'):
            peak = np.maximum(peak, np.abs(model.E @ q))
    return np.where(np.isnan(peak), np.inf, peak)


def gain_issue(model: Any, metadata: Mapping[str, Any] | None = None,
               factor: float = GAIN_FACTOR) -> str | None:
    """Why the model's steady state over its training inputs is absurd, or ``None``.

    Parameters
    ----------
    model : LinearROM
        Linear, or with a potential (:func:`peak_response`).
    metadata : dict, optional
        Holds the training ``envelope`` (default ``model.metadata``); without a recorded
        input range and output deviation nothing is checked.
    factor : float
        Allowed multiple of the largest training output deviation.
    """
    meta = model.metadata if metadata is None else metadata
    env = meta.get('envelope') if isinstance(meta, Mapping) else None
    if not isinstance(env, Mapping):
        return None
    m = int(model.n_inputs)
    u_min, u_max = _floats(env.get('u_min'), m), _floats(env.get('u_max'), m)
    dev = env.get('y_dev_max')
    if u_min is None or u_max is None or not isinstance(dev, (int, float)) \
            or isinstance(dev, bool) or not (math.isfinite(dev) and dev > 0):
        return None
    if not np.all(u_min <= u_max):
        return None
    samples = env.get('samples')
    horizon = int(samples) if isinstance(samples, int) and not isinstance(samples, bool) \
        and samples > 0 else None
    peak = peak_response(model, u_min, u_max, horizon)
    if not peak.size:
        return None
    i = int(np.argmax(np.where(np.isnan(peak), np.inf, peak)))
    worst = float(peak[i])
    if worst <= factor * dev:
        return None
    names = list(getattr(model, 'output_names', ()) or ())
    units = list(getattr(model, 'output_units', ()) or ())
    name = names[i] if i < len(names) else f'y{i + 1}'
    unit = f' {units[i]}' if i < len(units) and units[i] else ''
    if not math.isfinite(worst):
        return (f'absurd gain: the steady state is unbounded (I - A is singular), while the '
                f'training outputs moved at most {dev:.3g}{unit}')
    within = 'at steady state' if horizon is None else \
        f'within the training length ({horizon} steps)'
    return (f'absurd gain: inputs held within the training range move output {name} by '
            f'{worst:.3g}{unit} {within}, {worst / dev:.3g} x the largest training '
            f'deviation ({dev:.3g}{unit}; limit {factor:g} x)')


def _floats(values: Any, m: int) -> Array | None:
    if not isinstance(values, (list, tuple)) or len(values) != m:
        return None
    try:
        arr = np.array([float(v) for v in values], dtype=np.float64)
    except (TypeError, ValueError):
        return None
    return arr if bool(np.all(np.isfinite(arr))) else None
