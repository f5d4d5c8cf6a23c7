"""Reference centerline trajectories: from a file, or built in (wave, static bend, episode).

A reference is absolute outputs ``Y`` (p, k) in the model's output layout at times ``t``
(k,) in seconds; between samples it is interpolated linearly, after the last it is held.

Built-ins (``--reference`` on the command line):

* ``wave:f=2,wavelength=0.8,amplitude=auto`` -- the biological travelling wave of
  anguilliform swimming: the lateral (``z``) displacement of the point at arc position
  ``s = x / L`` is ``a(s) sin(2 pi (s / wavelength - f t))`` with an amplitude that grows
  towards the tail, ``a(s) = amplitude * s^2`` (clamped head: zero there); ``wavelength``
  in body lengths. ``amplitude=auto`` scales it into the robot's reach measured from the
  training data: ``reach`` (default 0.1) times the largest output deviation recorded in the
  model file (``metadata['envelope']['y_dev_max']``). ``ramp`` (s, default 0.2) fades it in.
* ``step:u=P1/P2/P3/P4/P5/P6,at=0.1`` -- a static bend: the embedded FOM's own steady
  state under the constant pressures ``u`` (Pa; simulated for ``settle`` seconds, default
  3), commanded from rest at ``at`` seconds.
* ``episode:PATH`` -- a feasible reference: the outputs of a recorded episode (a bag of the
  bag contract, converted on the fly, or a ``.npz`` with ``t`` and ``Y``).

A reference that moves at or above the Nyquist rate of the control step (a wave of
``f >= 1 / (2 h)``) is refused (:func:`sampling_problem`): sampled every ``h`` it is another,
slower motion (``wave:f=200`` at 10 ms: a static shape). A static target (a reference held
over the last fifth of its duration) that the model's steady state cannot reach within the
input bounds is controlled all the same, with a
:class:`~soft_rom.errors.ReferenceReachWarning` (:func:`reach_miss`).
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.data import all_finite
from soft_rom.errors import ConfigError, DimensionError

__all__ = ['REACH_TOLERANCE', 'Reference', 'check_moves', 'load_reference', 'parse_reference',
           'reach_miss', 'sampling_problem', 'step_reference', 'training_band',
           'training_deviation', 'wave_reference']

Array = NDArray[np.float64]

#: A static target of which the input bounds cut off more than this fraction of the commanded
#: deviation is out of reach (:func:`reach_miss`'s ``cut``).
REACH_TOLERANCE = 0.1


@dataclass(frozen=True)
class Reference:
    """A reference trajectory of absolute outputs.

    Attributes
    ----------
    t : ndarray, shape (k,)
        Increasing times (s).
    Y : ndarray, shape (p, k)
        Absolute outputs.
    label : str
        What it is, for reports.
    U : ndarray, shape (m, k) or None
        The inputs that produce it on the FOM, when known (feasible references).
    frequency : float or None
        The highest frequency of its motion (Hz), when known (a wave's ``f``): a control step
        whose Nyquist rate it reaches is refused (:func:`sampling_problem`).
    """

    t: Array
    Y: Array
    label: str = ''
    U: Array | None = None
    frequency: float | None = None

    def __post_init__(self) -> None:
        t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        Y = np.asarray(self.Y, dtype=np.float64)
        if Y.ndim != 2 or Y.shape[1] != t.size or t.size < 1:
            raise DimensionError(f'a reference needs t (k,) and Y (p, k) with k >= 1; got t '
                                 f'{t.shape} and Y {Y.shape}.')
        if not (all_finite(t) and all_finite(Y)):
            raise DimensionError('the reference has NaN or Inf in t or Y.')
        if t.size > 1 and np.any(np.diff(t) <= 0):
            raise DimensionError('the reference times t must increase.')
        object.__setattr__(self, 't', t)
        object.__setattr__(self, 'Y', Y)

    @property
    def n_outputs(self) -> int:
        """Number of outputs ``p``."""
        return int(self.Y.shape[0])

    @property
    def duration(self) -> float:
        """Time of the last sample (s)."""
        return float(self.t[-1])

    def at(self, times: ArrayLike) -> Array:
        """Reference outputs at ``times``, shape (p, len(times)); held beyond its ends."""
        tq = np.atleast_1d(np.asarray(times, dtype=np.float64))
        if self.t.size == 1:
            return np.repeat(self.Y, tq.size, axis=1)
        idx = np.clip(np.searchsorted(self.t, tq, side='right') - 1, 0, self.t.size - 2)
        t0, t1 = self.t[idx], self.t[idx + 1]
        w = np.clip((tq - t0) / (t1 - t0), 0.0, 1.0)
        return self.Y[:, idx] * (1 - w) + self.Y[:, idx + 1] * w


def _options(text: str, allowed: dict[str, Any], what: str) -> dict[str, Any]:
    out = dict(allowed)
    given: dict[str, str] = {}
    if not text:
        return out
    for item in text.split(','):
        key, sep, value = item.partition('=')
        key = key.strip()
        if not sep or key not in allowed:
            raise ConfigError(f'--reference {what}: unknown option {item!r}; options are '
                              f'{", ".join(f"{k}=" for k in allowed)}.')
        if key in given:
            raise ConfigError(f'--reference {what}: {key}= given twice ({given[key]!r} and '
                              f'{value.strip()!r}); give it once.')
        out[key] = given[key] = value.strip()
    return out


def _number(value: Any, name: str, what: str, *, lo: float = -math.inf,
            hi: float = math.inf) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f'--reference {what}: {name}={value!r} is not a number.') from None
    if not (math.isfinite(v) and lo <= v <= hi):
        raise ConfigError(f'--reference {what}: {name}={value!r} must be a finite number in '
                          f'[{lo:g}, {hi:g}].')
    return v


def _layout(model: Any) -> tuple[Array, Array, Array]:
    """Rows of the ``x`` and ``z`` components of each centerline point, and ``s = x / L``."""
    names = list(model.output_names)
    xs = [i for i, n in enumerate(names) if n.startswith('x')]
    zs = [i for i, n in enumerate(names) if n.startswith('z')]
    if not xs or len(xs) != len(zs):
        raise ConfigError('this reference needs a model whose outputs are the x and z '
                          f'coordinates of centerline points (x1.., z1..); got {names[:4]}...')
    x_rest = np.asarray(model.y_ref, dtype=np.float64)[xs]
    length = float(np.max(x_rest) - np.min(x_rest)) or 1.0
    s = (x_rest - np.min(x_rest)) / length
    return np.array(xs), np.array(zs), s


def wave_reference(model: Any, duration: float, *, f: float = 2.0, wavelength: float = 0.8,
                   amplitude: float | None = None, reach: float = 0.1, ramp: float = 0.2,
                   dt: float = 1e-3) -> Reference:
    """The biological travelling wave (see the module docstring) in ``model``'s layout."""
    xs, zs, s = _layout(model)
    if amplitude is None:
        dev = training_deviation(model)
        if dev is None:
            raise ConfigError('--reference wave: the model file records no output range; give '
                              'amplitude= in output units.')
        amplitude = reach * float(dev)
    t = np.asarray(np.arange(int(round(duration / dt)) + 1) * dt, dtype=np.float64)
    fade = np.clip(t / ramp, 0.0, 1.0) if ramp > 0 else np.ones_like(t)
    Y = np.repeat(np.asarray(model.y_ref, dtype=np.float64)[:, None], t.size, axis=1)
    a = amplitude * s ** 2
    Y[zs] += a[:, None] * np.sin(2 * np.pi * (s[:, None] / wavelength - f * t[None, :])) * fade
    label = (f'wave f={f:g} Hz, wavelength={wavelength:g} L, tail amplitude '
             f'{amplitude * 1e3:.3g} mm')
    return Reference(t=t, Y=Y, label=label, frequency=float(f))


def step_reference(model: Any, u: ArrayLike, duration: float, *, at: float = 0.1,
                   settle: float = 3.0, plant: Any = None, dt: float = 1e-3) -> Reference:
    """A static bend: the FOM's steady state under constant pressures ``u``, from ``at`` s.

    Parameters
    ----------
    model : LinearROM
        Its output names give the layout (``x1..``, ``z1..``).
    u : ndarray, shape (6,)
        Chamber pressures (Pa).
    plant : EelModel, optional
        The FOM (default: the embedded eel at resolution 1).
    """
    from soft_rom.sim import EelModel
    u = np.asarray(u, dtype=np.float64).reshape(-1)
    eel = plant if plant is not None else EelModel()
    if u.shape != (eel.n_chambers,) or not all_finite(u):
        raise ConfigError(f'--reference step: u needs {eel.n_chambers} finite pressures '
                          f'separated by "/"; got {u.tolist()}.')
    if np.max(np.abs(u)) > 1e7:
        raise ConfigError(f'--reference step: pressures of at most 1e7 Pa (as simulate '
                          f'--amplitude); got {u.tolist()}.')
    label = f'static bend u=[{", ".join(f"{v / 1e3:g}" for v in u)}] kPa from {at:g} s'
    t = np.asarray(np.arange(int(round(duration / dt)) + 1) * dt, dtype=np.float64)
    if not t[-1] >= at:              # said before the FOM's settling run (seconds), not after
        raise ConfigError(f"the reference {label!r} does not leave the model's rest output "
                          f"within the run's {duration:g} s: the tracking error, relative to "
                          'that deviation, would be undefined. Give an earlier at=, or a '
                          'longer --duration.')
    n = max(1, int(round(settle / dt)))
    res = eel.simulate(np.repeat(u[:, None], n, axis=1), n, dt)
    y_end = _model_outputs(model, res.centerline[:, :, -1])
    Y = np.where(t[None, :] < at, np.asarray(model.y_ref)[:, None], y_end[:, None])
    return Reference(t=t, Y=Y, label=label, U=np.where(t[None, :] < at, 0.0, u[:, None]))


def _model_outputs(model: Any, centerline: Array) -> Array:
    """``centerline`` (N, 3) as the model's output vector (names ``x<i>``/``y<i>``/``z<i>``)."""
    out = np.empty(len(model.output_names))
    for row, name in enumerate(model.output_names):
        comp, idx = name[:1], name[1:]
        if comp not in 'xyz' or not idx.isdigit() or not 1 <= int(idx) <= centerline.shape[0]:
            raise ConfigError(f'output {name!r} is not a centerline coordinate of the embedded '
                              f'eel (x1..x{centerline.shape[0]}, z1..); the FOM cannot be the '
                              'plant of this model.')
        out[row] = centerline[int(idx) - 1, 'xyz'.index(comp)]
    return out


def load_reference(path: str | Path, model: Any) -> Reference:
    """A reference file: ``.npz`` with ``t`` (k,) s and ``Y`` (p, k) absolute outputs.

    Also reads a bag (``episode:``) through :func:`soft_rom.convert.convert_episode`.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f'reference {path} does not exist.')
    if path.is_dir() or path.suffix in ('.mcap', '.db3'):     # a bag (folder or file)
        return _episode_reference(path, model)
    from soft_rom.models.archive import read_user_arrays
    z = read_user_arrays(path, 'reference', ('t', 'Y', 'U'))
    if 't' not in z or 'Y' not in z:
        raise ConfigError(f'reference {path} must hold arrays t (k,) and Y (p, k); '
                          f'{" and ".join(n for n in ("t", "Y") if n not in z)} missing.')
    t, Y = np.asarray(z['t'], dtype=np.float64), np.asarray(z['Y'], dtype=np.float64)
    U = np.asarray(z['U'], dtype=np.float64) if 'U' in z else None
    ref = Reference(t=t, Y=Y, label=path.name,
                    U=U if U is not None and U.ndim == 2 and U.shape[1] == t.size else None)
    check_reference(ref, model)
    return ref


def _episode_reference(bag: Path, model: Any) -> Reference:
    from soft_rom.convert.api import read_episode
    ep, _report = read_episode(bag)
    names = list(ep.metadata.get('output_names') or [])
    if names and names != list(model.output_names):
        raise ConfigError(f'episode {bag}: its outputs ({", ".join(names[:3])}...) are not the '
                          f'model\'s ({", ".join(model.output_names[:3])}...).')
    ref = Reference(t=ep.t - ep.t[0], Y=ep.Y, label=f'episode {bag.name}', U=ep.U)
    check_reference(ref, model)
    return ref


def check_reference(ref: Reference, model: Any) -> None:
    """Refuse a reference whose size is not the model's output count."""
    if ref.n_outputs != model.n_outputs:
        raise DimensionError(f'the reference has {ref.n_outputs} outputs; the model has '
                             f'{model.n_outputs} ({", ".join(model.output_names[:3])}...).')


def training_deviation(model: Any) -> float | None:
    """The training data's largest output deviation recorded in the model file, if any."""
    env = model.metadata.get('envelope') if isinstance(model.metadata, dict) else None
    dev = env.get('y_dev_max') if isinstance(env, dict) else None
    if isinstance(dev, (int, float)) and math.isfinite(dev) and dev > 0:
        return float(dev)
    return None


def training_band(model: Any) -> float | None:
    """The training outputs' bandwidth (Hz) recorded in the model file, if any.

    ``metadata['envelope']['y_band_hz']`` (:func:`soft_rom.envelope.training_envelope`);
    model files fitted before it was recorded have none.
    """
    env = model.metadata.get('envelope') if isinstance(model.metadata, dict) else None
    band = env.get('y_band_hz') if isinstance(env, dict) else None
    if isinstance(band, (int, float)) and math.isfinite(band) and band > 0:
        return float(band)
    return None


def check_moves(ref: Reference, model: Any, duration: float | None = None) -> None:
    """Refuse a reference that does not leave the model's rest output within ``duration``.

    The tracking error is relative to that deviation (``‖Y − Y_ref‖ / ‖Y_ref − y_ref‖``):
    a reference at rest over the run (a step after its end, the rest output itself) leaves
    it undefined, and one so large that its deviation overflows leaves it meaningless. A
    reference moving less than 1/1000 or more than 100 times the training data's largest
    deviation (when the model file records it) is in other units than the model.
    """
    dur = ref.duration if duration is None else float(duration)
    times = np.linspace(min(0.0, dur), dur, max(2, min(100_001, int(abs(dur) / 1e-3) + 1)))
    y_ref = np.asarray(model.y_ref, dtype=np.float64)
    with np.errstate(over='ignore', invalid='ignore'):
        dev = float(np.max(np.abs(ref.at(times) - y_ref[:, None])))
        norm = float(np.linalg.norm(ref.Y - y_ref[:, None]))
    if not (math.isfinite(dev) and math.isfinite(norm)):
        raise ConfigError(f'the reference {ref.label!r} is too large: its deviation from the '
                          "model's rest output overflows.")
    tol = 1e-9 * max(1.0, float(np.max(np.abs(y_ref), initial=0.0)))
    if dev <= tol:
        raise ConfigError(f"the reference {ref.label!r} does not leave the model's rest output "
                          f"within the run's {dur:g} s (largest deviation {dev:.3g}): the "
                          'tracking error, relative to that deviation, would be undefined. '
                          'Give a reference that moves, or a longer --duration.')
    trained = training_deviation(model)
    if trained is not None and not 1e-3 * trained <= dev <= 100 * trained:
        units = ', '.join(sorted(set(getattr(model, 'output_units', None) or ()))) or '?'
        raise ConfigError(f'the reference {ref.label!r} moves up to {dev:.3g} from the rest '
                          f"output, {dev / trained:.2g} x the training data's largest deviation"
                          f" ({trained:.3g}): give it in the model's output units ({units}), "
                          'within its reach.')


def sampling_problem(ref: Reference, step: float) -> str:
    """Why ``ref`` cannot be sampled every ``step`` seconds (its Nyquist rate), or ``''``."""
    f = ref.frequency
    if f is None or not (f > 0 and step > 0) or f < 0.5 / step:
        return ''
    fs = 1.0 / step
    alias = abs(f - round(f / fs) * fs)
    seen = 'a static shape' if alias < 1e-9 * fs else f'a {alias:.3g} Hz motion'
    return (f'the reference {ref.label!r} moves at {f:g} Hz, at or above the Nyquist rate '
            f'({0.5 * fs:g} Hz) of the {step * 1e3:g} ms control step: sampled every step it '
            f'is {seen}. Give a frequency below {0.5 * fs:g} Hz, or a shorter control step.')


def reach_miss(ref: Reference, gain: Array, lo: Array, hi: Array, y_ref: Array
               ) -> tuple[float, float, float] | None:
    """How far a static target lies outside a model's steady-state reach, or ``None``.

    A reference held over the last fifth of its duration (a step, a bend) has a static
    target ``r``; ``gain`` (p, m) is the model's steady-state gain, ``lo``/``hi`` the input
    bounds. Returns ``(bounded, free, cut)``: ``min ‖gain u − (r − y_ref)‖ / ‖r − y_ref‖``
    over ``lo <= u <= hi`` (:func:`scipy.optimize.lsq_linear`, ``u_b``) and over any ``u``
    (``u_f``), and ``‖gain (u_b − u_f)‖ / ‖r − y_ref‖``, the part of the target in the
    model's steady shapes that the bounds cut off (``bounded² = free² + cut²``; ``free`` is
    the model's shape error, which the offset-free estimate absorbs, ``cut`` is not).
    ``None`` for a reference that moves at its end or does not leave ``y_ref``.
    """
    from scipy.optimize import lsq_linear
    end = ref.t >= ref.t[-1] - 0.2 * (ref.t[-1] - ref.t[0])
    target = ref.Y[:, -1]
    scale = max(1.0, float(np.max(np.abs(target))))
    dev = target - np.asarray(y_ref, dtype=np.float64)
    norm = float(np.linalg.norm(dev))
    if np.any(np.abs(ref.Y[:, end] - target[:, None]) > 1e-9 * scale) or norm <= 1e-9 * scale \
            or not np.all(np.isfinite(gain)):
        return None
    bounded = lsq_linear(gain, dev, bounds=(lo, hi), method='bvls')
    free = np.linalg.lstsq(gain, dev, rcond=None)[0]
    return (float(np.linalg.norm(gain @ bounded.x - dev)) / norm,
            float(np.linalg.norm(gain @ free - dev)) / norm,
            float(np.linalg.norm(gain @ (bounded.x - free))) / norm)


def parse_reference(spec: str, model: Any, *, duration: float | None = None,
                    plant: Any = None) -> Reference:
    """``--reference``: a path (``.npz``), or ``wave:…``, ``step:…``, ``episode:PATH``."""
    kind, sep, rest = spec.partition(':')
    if sep and kind == 'episode':
        return load_reference(rest, model)
    if sep and kind == 'wave':
        o = _options(rest, {'f': '2', 'wavelength': '0.8', 'amplitude': 'auto',
                            'reach': '0.1', 'ramp': '0.2'}, 'wave')
        amp = None if o['amplitude'] == 'auto' else _number(o['amplitude'], 'amplitude',
                                                            'wave', lo=0.0, hi=1e3)
        return wave_reference(model, duration or 2.0,
                              f=_number(o['f'], 'f', 'wave', lo=0.0, hi=1e3),
                              wavelength=_number(o['wavelength'], 'wavelength', 'wave',
                                                 lo=1e-3, hi=1e3),
                              amplitude=amp,
                              reach=_number(o['reach'], 'reach', 'wave', lo=0.0, hi=10.0),
                              ramp=_number(o['ramp'], 'ramp', 'wave', lo=0.0, hi=1e3))
    if sep and kind == 'step':
        o = _options(rest, {'u': '', 'at': '0.1', 'settle': '3'}, 'step')
        if not o['u']:
            raise ConfigError('--reference step: give the pressures, e.g. '
                              'step:u=20e3/-20e3/0/0/0/0 (Pa, one per chamber).')
        try:
            u = [float(v) for v in o['u'].split('/')]
        except ValueError:
            raise ConfigError(f'--reference step: u={o["u"]!r} must be numbers separated by '
                              '"/".') from None
        return step_reference(model, u, duration or 2.0,
                              at=_number(o['at'], 'at', 'step', lo=0.0, hi=1e4),
                              settle=_number(o['settle'], 'settle', 'step', lo=1e-3, hi=600.0),
                              plant=plant)
    if sep and kind not in ('episode', 'wave', 'step') and len(kind) > 1:
        raise ConfigError(f'--reference {spec!r}: unknown kind {kind!r}; give a .npz file, '
                          'wave:..., step:u=... or episode:BAG.')
    return load_reference(spec, model)
