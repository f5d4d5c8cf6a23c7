"""The closed loop in one process: the embedded FOM as the plant, a sensor, the controller.

The plant (:class:`FOMPlant`, the eel FEM of :mod:`soft_rom.sim` stepped one input at a time)
runs at its own step (1 ms); a motion-capture-like :class:`Sensor` samples its centerline at
``rate`` Hz with Gaussian noise (default 120 Hz, 0.5 mm), stamped with the plant sample's
time; the :class:`~soft_rom.control.controller.Controller` sees only those measurements and
computes a command every control step, held by the plant until the next one (zero-order
hold). Nothing of the FEM state reaches the controller.

Per plant sample ``j`` (time ``t_j``): the noise-free output ``Y[:, j]`` is recorded; a
camera frame due in ``[t_j, t_{j+1})`` is measured from it and given to the controller; on
a control tick the controller computes the command; ``U[:, j]`` is the command in force, and
the plant steps with it. ``soft-rom simulate --inputs`` with the recorded ``t`` and ``U``
runs the same plant on the same inputs and reproduces ``Y``.

:func:`open_loop_plan` runs the same controller with the ROM itself as the plant (no noise):
the pressures an MPC would apply if the model were right, for comparison.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import json
import math
from pathlib import Path
import time
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.control.controller import Controller
from soft_rom.control.estimator import EstimatorConfig
from soft_rom.control.mpc import MPCConfig, require_linear
from soft_rom.control.reference import _model_outputs, check_moves, Reference
from soft_rom.data import as_signal
from soft_rom.errors import ConfigError, DimensionError
from soft_rom.metrics import relative_deviation_error

__all__ = ['ClosedLoopResult', 'FOMPlant', 'ROMPlant', 'Sensor', 'check_plant_units',
           'open_loop_plan', 'run_closed_loop', 'simulate_inputs']

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Sensor:
    """A motion-capture-like centerline sensor.

    Parameters
    ----------
    rate : float
        Frames per second (default 120 Hz).
    noise : float
        Standard deviation of the Gaussian noise per coordinate (output units; 0.5 mm).
    seed : int
        Seed of the noise.
    """

    rate: float = 120.0
    noise: float = 5e-4
    seed: int = 0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rate) and self.rate > 0):
            raise ConfigError(f'sensor rate must be > 0 Hz; got {self.rate!r}.')
        if not (math.isfinite(self.noise) and self.noise >= 0):
            raise ConfigError(f'sensor noise must be >= 0; got {self.noise!r}.')


def check_plant_units(model: Any) -> None:
    """The embedded eel takes pressures in Pa and gives its centerline in m: so must the model.

    A model fitted on a set converted in other units (kPa, mm) would have its commands
    applied in the wrong units and its outputs compared with the wrong numbers.
    """
    for kind, units, want in (('inputs', getattr(model, 'input_units', None), 'Pa'),
                              ('outputs', getattr(model, 'output_units', None), 'm')):
        other = sorted({u for u in (units or []) if u and u != want})
        if other:
            raise ConfigError(f'the model\'s {kind} are in {", ".join(other)}; the embedded '
                              f'eel plant works in {want}. Fit the model on a training set '
                              f"converted in {want} (the bag mapping's units and scale).")


class FOMPlant:
    """The embedded eel FOM as a plant: one step at a time, outputs in a model's layout.

    Parameters
    ----------
    model : LinearROM
        Whose output names (``x1..``, ``z1..``) give the layout of :meth:`output`.
    eel : EelModel, optional
        Default: the embedded eel at resolution 1.
    dt : float
        Plant step (s), 1 ms.
    jacobian : str
        As :meth:`soft_rom.sim.EelModel.simulate`.
    """

    def __init__(self, model: Any, eel: Any = None, *, dt: float = 1e-3,
                 jacobian: str = 'rest') -> None:
        from soft_rom.sim import EelModel
        self.eel = eel if eel is not None else EelModel()
        self.model = model
        self.dt = float(dt)
        self.jacobian = jacobian
        check_plant_units(model)
        self._stepper = self.eel.stepper(self.dt, jacobian=jacobian)
        _model_outputs(model, self._stepper.centerline())      # the layout fits: checked
        self.n_inputs = self.eel.n_chambers

    def output(self) -> Array:
        """Noise-free output at the current sample, shape (p,)."""
        return _model_outputs(self.model, self._stepper.centerline())

    def step(self, u: ArrayLike) -> None:
        """Advance one plant step with ``u`` (one pressure per chamber, Pa) held."""
        self._stepper.step(_input_vector(u, self.n_inputs))


class ROMPlant:
    """A linear ROM as the plant (its native step): for open-loop plans and tests."""

    def __init__(self, model: Any, *, dt: float | None = None) -> None:
        require_linear(model, 'ROMPlant')
        self.model = model
        self.dt = float(model.dt if dt is None else dt)
        sys_ = model.discretize(self.dt)
        self.A, self.B, self.C, self.D = sys_.A, sys_.B, sys_.C, sys_.D
        self.x = np.zeros(self.A.shape[0])
        self.u = np.zeros(self.B.shape[1])
        self.n_inputs = self.B.shape[1]

    def output(self) -> Array:
        return self.C @ self.x + self.D @ self.u + self.model.y_ref

    def step(self, u: ArrayLike) -> None:
        self.u = _input_vector(u, self.n_inputs)
        self.x = self.A @ self.x + self.B @ self.u


def _input_vector(u: ArrayLike, m: int) -> Array:
    """``u`` as ``m`` finite inputs, or :class:`DimensionError`."""
    try:
        v = np.asarray(u, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise DimensionError(f'the plant input must be {m} numbers; {err}.') from err
    if v.shape != (m,) or not np.all(np.isfinite(v)):
        raise DimensionError(f'the plant input must be {m} finite values (one per input); got '
                             f'shape {v.shape}' + ('' if v.shape != (m,) else ' with NaN/Inf')
                             + '.')
    return v


@dataclass
class ClosedLoopResult:
    """A closed-loop run (arrays ``(n_channels, n_samples)`` on the plant's grid).

    Attributes
    ----------
    t : ndarray, shape (k,)
        Plant sample times (s).
    U : ndarray, shape (m, k)
        Pressures applied (held over ``[t_j, t_{j+1})``).
    Y : ndarray, shape (p, k)
        The plant's noise-free outputs.
    Y_ref : ndarray, shape (p, k)
        The reference at ``t``.
    t_meas : ndarray, shape (k_m,)
    Y_meas : ndarray, shape (p, k_m)
        What the controller saw.
    t_control : ndarray, shape (n,)
        Control tick times.
    solve_s, step_s : ndarray, shape (n,)
        QP solve and whole control step wall times (s).
    step_cpu_s : ndarray, shape (n,)
        Whole control step thread CPU times (s).
    status : ndarray of str, shape (n,)
        Status of each control step.
    u_min, u_max : ndarray, shape (m,)
    y_ref : ndarray, shape (p,)
        The model's output reference (for deviation errors).
    info : dict
    """

    t: Array
    U: Array
    Y: Array
    Y_ref: Array
    t_meas: Array
    Y_meas: Array
    t_control: Array
    solve_s: Array
    step_s: Array
    step_cpu_s: Array
    status: NDArray[np.str_]
    u_min: Array
    u_max: Array
    y_ref: Array
    info: dict[str, Any] = field(default_factory=dict)

    def tracking_error(self, t_from: float = 0.0) -> float:
        """``||Y - Y_ref||_F / ||Y_ref - y_ref||_F`` over samples at ``t >= t_from``."""
        keep = self.t >= t_from - 1e-12
        return relative_deviation_error(self.Y_ref[:, keep], self.Y[:, keep], self.y_ref)

    def summary(self) -> dict[str, Any]:
        """The figures of ``summary.json``."""
        solves = self.solve_s[self.solve_s > 0]

        def pct(a: Array) -> dict[str, float | None]:
            if a.size == 0:
                return {'p50_ms': None, 'p99_ms': None, 'max_ms': None}
            return {'p50_ms': float(np.percentile(a, 50) * 1e3),
                    'p99_ms': float(np.percentile(a, 99) * 1e3),
                    'max_ms': float(np.max(a) * 1e3)}

        statuses, counts = np.unique(self.status, return_counts=True)
        period = float(self.info.get('control_step_s', 0.0)) or None
        step = pct(self.step_s)
        return {
            'tracking_deviation_error': _finite(self.tracking_error()),
            'tracking_deviation_error_after_1s': _finite(self.tracking_error(1.0))
            if self.t[-1] > 1.0 else None,
            'solve': pct(solves), 'control_step': step,
            'control_step_cpu': pct(self.step_cpu_s),
            'control_step_p99_fraction_of_period': (
                step['p99_ms'] / (1e3 * period) if period and step['p99_ms'] is not None
                else None),
            'status_counts': {str(s): int(c) for s, c in zip(statuses, counts)},
            'saturated_fraction': float(np.mean(
                (self.U <= self.u_min[:, None] + 1e-9 * np.abs(self.u_min[:, None]) + 1e-9)
                | (self.U >= self.u_max[:, None] - 1e-9 * np.abs(self.u_max[:, None]) - 1e-9))),
            **{k: v for k, v in self.info.items() if not isinstance(v, np.ndarray)},
        }

    def save(self, path: str | Path) -> Path:
        """Write ``closed_loop.npz`` (plain arrays; read with ``allow_pickle=False``)."""
        path = Path(path)
        tmp = path.with_name(f'.{path.name}.tmp')
        with open(tmp, 'wb') as fh:
            np.savez(fh, t=self.t, U=self.U, Y=self.Y, Y_ref=self.Y_ref, t_meas=self.t_meas,
                     Y_meas=self.Y_meas, t_control=self.t_control, solve_s=self.solve_s,
                     step_s=self.step_s, step_cpu_s=self.step_cpu_s,
                     status=self.status.astype('U16'), u_min=self.u_min, u_max=self.u_max,
                     y_ref=self.y_ref)
        tmp.replace(path)
        return path


def _finite(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def run_closed_loop(model: Any, reference: Reference, *, plant: Any = None,
                    mpc: MPCConfig | None = None, estimator: EstimatorConfig | None = None,
                    sensor: Sensor | None = None, duration: float | None = None,
                    progress: Any = None) -> ClosedLoopResult:
    """Run the closed loop (see the module docstring).

    Parameters
    ----------
    model : LinearROM
    reference : Reference
    plant : FOMPlant or ROMPlant, optional
        Default: a fresh :class:`FOMPlant` for ``model``.
    mpc, estimator : configs
    sensor : Sensor
        Default ``Sensor()``; a noise of 0 gives exact measurements.
    duration : float, optional
        Seconds to run (default: the reference's duration).
    progress : callable, optional
        Called with the fraction done now and then.
    """
    if duration is not None and not (math.isfinite(duration) and duration > 0):
        raise ConfigError(f'the closed loop needs a duration > 0 s; got {duration!r}.')
    sensor = sensor or Sensor()
    if estimator is None:
        estimator = EstimatorConfig(measurement_noise=max(sensor.noise, 1e-5),
                                    sensor_rate=sensor.rate)
    ctl = Controller(model, mpc, estimator)
    if reference.n_outputs != ctl.mpc.p:
        raise ConfigError(f'the reference has {reference.n_outputs} outputs; the model has '
                          f'{ctl.mpc.p}.')
    check_moves(reference, model, duration)
    refused = ctl.set_reference(reference)     # too fast for the control step
    if refused:
        raise ConfigError(refused)
    plant = plant if plant is not None else FOMPlant(model)
    dt = float(plant.dt)
    every = _control_every(ctl.h, dt)
    duration = reference.duration if duration is None else float(duration)
    k = max(1, int(round(duration / dt)))
    rng = np.random.default_rng(sensor.seed)
    t = np.asarray(np.arange(k) * dt, dtype=np.float64)
    p, m = ctl.mpc.p, ctl.mpc.m
    Y = np.empty((p, k))
    U = np.empty((m, k))
    is_frame = _frame_mask(k, dt, sensor.rate)
    t_meas, Y_meas = [], []
    t_ctl, solve_s, step_s, step_cpu, status = [], [], [], [], []
    ctl.start(0.0)
    t_start = time.perf_counter()
    for j in range(k):
        y = plant.output()
        Y[:, j] = y
        if is_frame[j]:
            ym = y + sensor.noise * rng.standard_normal(p) if sensor.noise > 0 else y.copy()
            t_meas.append(t[j])
            Y_meas.append(ym)
            ctl.measure(ym, float(t[j]))
        if j % every == 0:
            cmd = ctl.step(float(t[j]))
            t_ctl.append(t[j])
            solve_s.append(cmd.solve_s)
            step_s.append(cmd.step_s)
            step_cpu.append(cmd.step_cpu_s)
            status.append(cmd.status)
        U[:, j] = ctl.u
        plant.step(ctl.u)
        if progress is not None and j % 100 == 0:
            progress(j / k)
    info = _loop_info(model, reference, ctl, sensor, dt, k, time.perf_counter() - t_start)
    return ClosedLoopResult(
        t=t, U=U, Y=Y, Y_ref=reference.at(t), t_meas=np.array(t_meas),
        Y_meas=np.array(Y_meas).T.reshape(p, -1), t_control=np.array(t_ctl),
        solve_s=np.array(solve_s), step_s=np.array(step_s), step_cpu_s=np.array(step_cpu),
        status=np.array(status, dtype='U16'),
        u_min=ctl.mpc.lo.copy(), u_max=ctl.mpc.hi.copy(), y_ref=np.asarray(model.y_ref).copy(),
        info=info)


def _control_every(h: float, dt: float) -> int:
    """Plant steps per control step (the control step must be a whole multiple of ``dt``)."""
    ratio = h / dt
    every = int(round(ratio))
    if every < 1 or abs(ratio - every) > 1e-6:
        raise ConfigError(f'the control step {h:g} s must be a whole multiple of the plant '
                          f'step {dt:g} s.')
    return every


def _frame_mask(k: int, dt: float, rate: float) -> NDArray[np.bool_]:
    """Which of ``k`` plant steps of ``dt`` the sensor sees at ``rate`` frames per second."""
    frames = np.floor(np.arange(0, k * dt * rate + 1e-9) / rate / dt + 1e-9).astype(np.int64)
    frames = np.unique(frames[frames < k])
    is_frame = np.zeros(k, dtype=bool)
    is_frame[frames] = True
    return is_frame


def _loop_info(model: Any, reference: Reference, ctl: Controller, sensor: Sensor, dt: float,
               k: int, wall: float) -> dict[str, Any]:
    """The ``info`` of a :class:`ClosedLoopResult`: settings, duration and wall time."""
    return {'method': str(model.method), 'r': int(model.r), 'reference': reference.label,
            'control_step_s': ctl.h, 'horizon_steps': ctl.mpc.N, 'plant_step_s': dt,
            'sensor_rate_hz': sensor.rate, 'sensor_noise': sensor.noise,
            'sensor_seed': sensor.seed, 'qp_solver': ctl.mpc.solver.name,
            'duration_s': k * dt, 'wall_s': wall,
            'measurements_dropped': ctl.counters.measurements_dropped}


def open_loop_plan(model: Any, reference: Reference, *, mpc: MPCConfig | None = None,
                   duration: float | None = None, dt: float = 1e-3) -> Array:
    """The pressures the same MPC applies when the ROM itself is the plant, shape (m, k).

    The controller sees the ROM's exact outputs; applied to the FOM afterwards these
    pressures are the controller run open loop.
    """
    res = run_closed_loop(model, reference, plant=ROMPlant(model, dt=dt), mpc=mpc,
                          sensor=Sensor(noise=0.0), duration=duration)
    return res.U


def simulate_inputs(model: Any, U: ArrayLike, *, dt: float = 1e-3, eel: Any = None) -> Array:
    """The FOM's noise-free outputs in ``model``'s layout for pressures ``U`` (m, k)."""
    plant = FOMPlant(model, eel, dt=dt)
    U = as_signal('U', U, rows=plant.n_inputs)
    if not np.all(np.isfinite(U)):
        raise DimensionError(f'U has {int(np.count_nonzero(~np.isfinite(U)))} NaN/Inf '
                             'value(s); the plant needs finite pressures.')
    Y = np.empty((len(model.output_names), U.shape[1]))
    for j in range(U.shape[1]):
        Y[:, j] = plant.output()
        plant.step(U[:, j])
    return Y


def write_summary(path: Path, summary: dict[str, Any]) -> None:
    """``summary.json`` (strict JSON)."""
    path.write_text(json.dumps(summary, indent=2, allow_nan=False), encoding='utf-8')
