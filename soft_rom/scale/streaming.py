"""Reduce once, then fit: LOpInf, DMDc and ERA/OKID ROMs from training sets larger than memory.

The data flow one way, in three steps, each a function of this module:

1. :func:`open_training_data` -- episodes with ``U``, ``Y``, ``t`` in memory and ``Q`` left
   lazy on disk, and the references ``q_ref``, ``y_ref``;
2. :func:`reduce_streaming` -- the *only* read of the snapshots: the streaming POD
   (:class:`~soft_rom.scale.pod.StreamingPOD`, 2--3 passes over the data, locally or on a
   Dask cluster) leaves a :class:`ReducedData` (POD coordinates of every episode, inputs,
   outputs) in memory;
3. :func:`fit_reduced_model` -- one ROM from the reduced data, as many times as wanted.

Step 3 hands the reduced data to the same learner entry points the in-memory fits use:

* **LOpInf** -- the POD pass also yields :math:`\\hat Q_i = V_r^T (Q_i - q_{ref})` for every
  episode (no separate projection pass); they go to
  :meth:`soft_rom.learners.lopinf.LOpInf.fit_reduced` (derivatives, the SPD-constrained
  operator fit and the output fit, in memory on ``(r, k)`` arrays), exactly as in
  :func:`soft_rom.fitting.fit_models`.
* **DMDc** -- with :math:`X \\approx W Z` (``W`` the ``l`` leading POD modes, orthonormal,
  ``Z`` the streamed coordinates, ``l >= p``), the stacked matrix
  :math:`\\Omega = [X; U] = \\mathrm{diag}(W, I) [Z; U]`, so the SVDs of ``Ω`` and of
  ``Q'`` are those of the small ``[Z; U]`` and ``Z'`` with left factors multiplied by
  ``W``; every DMDc operator (Proctor et al. 2016; paper sec. 2.3) is unchanged by that
  orthonormal factor. The result is *exactly* the in-memory DMDc when the snapshots lie
  in the span of the ``l`` modes, and otherwise DMDc of the snapshots projected on them
  (error of order :math:`\\sigma_{l+1}`). The unit-invariant scaling of
  :class:`soft_rom.learners.dmdc.DMDc` is reproduced with the *full* state RMS measured
  in the stream; the operators come from the learner's
  :func:`~soft_rom.learners.dmdc.dmdc_reduced_operators`.
* **ERA/OKID** needs only inputs and outputs (small) and never reads the snapshots:
  :meth:`soft_rom.learners.era.ERAOKID.fit` on one episode.

:func:`fit_streaming` runs the three steps for one model. Several models from one pass::

    red = reduce_streaming('train.zarr', n_coords=60)
    models = [fit_reduced_model(red, 'lopinf', r) for r in (4, 8, 16)]

(This module was ``soft_rom.scale.fit``; that name still imports, for one release.)
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
import time
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.data import Episode
from soft_rom.errors import ConfigError, DimensionError
from soft_rom.metrics import relative_error
from soft_rom.models import DiscreteModel, LinearROM
from soft_rom.scale.blocks import DEFAULT_BLOCK_BYTES, Executor, LocalExecutor, SnapshotSet
from soft_rom.scale.pod import StreamingPOD

__all__ = [
    'ColumnWindow',
    'ReducedData',
    'TrainingData',
    'fit_reduced_model',
    'fit_streaming',
    'make_executor',
    'open_training_data',
    'reduce_streaming',
]

Array = NDArray[np.float64]
METHODS = ('lopinf', 'dmdc', 'era')


class ColumnWindow:
    """Lazy view of columns ``[0, stop)`` of an on-disk ``(n, k)`` array (no data read).

    ``Episode.slice`` would read a zarr array eagerly; this keeps training-time limits
    (``t_max``) lazy for the streaming passes and for Dask.
    """

    def __init__(self, array: Any, stop: int) -> None:
        self.array = array
        self.stop = int(stop)
        self.shape = (int(array.shape[0]), self.stop)
        self.chunks = getattr(array, 'chunks', None)
        self.dtype = getattr(array, 'dtype', np.dtype(np.float64))

    def __getitem__(self, key: Any) -> Any:
        rows, cols = key
        a, b, step = cols.indices(self.stop)
        if step != 1:
            raise DimensionError('ColumnWindow supports contiguous column slices only.')
        return self.array[rows, a:b]

    def to_dask(self) -> Any:
        """The window as a dask array (the stored array's own, else ``from_zarr``)."""
        import dask.array as da
        if hasattr(self.array, 'to_dask'):      # a training set's checked StoredArray
            base = self.array.to_dask()
        elif type(self.array).__module__.startswith('zarr'):
            base = da.from_zarr(self.array)
        else:
            base = da.from_array(self.array)
        return base[:, :self.stop]


@dataclass
class TrainingData:
    """Episodes (``U``, ``Y``, ``t`` in memory, ``Q`` lazy) and their common reference.

    Attributes
    ----------
    episodes : list of Episode
    q_ref : ndarray, shape (n,) or None
    y_ref : ndarray, shape (p,)
    names : dict
        ``input_names``, ``input_units``, ``output_names``, ``output_units`` (may be None).
    provenance : dict
    """

    episodes: list[Episode]
    q_ref: Array | None
    y_ref: Array
    names: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)

    @property
    def dt(self) -> float:
        """Common sample time (seconds)."""
        dts = [ep.dt for ep in self.episodes]
        if any(abs(d - dts[0]) > 1e-6 * dts[0] for d in dts):
            raise DimensionError(f'episodes have different sample times {dts}; resample first.')
        return float(dts[0])

    def model_names(self) -> dict[str, Any]:
        """The names and units known for the model (keyword arguments of the learners)."""
        return {k: v for k, v in self.names.items() if v is not None}


def open_training_data(data: Any, *, episodes: Sequence[str] | None = None,
                       t_max: float | None = None, q_ref: ArrayLike | None = None,
                       y_ref: ArrayLike | None = None) -> TrainingData:
    """Gather episodes from a training set (path or ``TrainingSet``) or a list of Episodes.

    Parameters
    ----------
    data : str, os.PathLike, TrainingSet, or sequence of Episode
    episodes : sequence of str, optional
        Names of the episodes to use (default all).
    t_max : float, optional
        Use only samples with ``t < t_max`` (seconds from each episode's start), kept lazy.
    q_ref, y_ref : array_like, optional
        References; default those stored in the training set, else the first sample of the
        first episode.
    """
    names: dict[str, Any] = {}
    provenance: dict[str, Any] = {}
    ts_q_ref = ts_y_ref = None
    if isinstance(data, (str, bytes)) or hasattr(data, '__fspath__'):
        from soft_rom.dataset import TrainingSet
        data = TrainingSet.open(data)
    if hasattr(data, 'episode_names'):
        ts = data
        wanted = list(ts.episode_names) if episodes is None else list(episodes)
        unknown = [e for e in wanted if e not in ts.episode_names]
        if unknown:
            raise ConfigError(f'unknown episodes {unknown}; the training set has '
                              f'{list(ts.episode_names)}.')
        eps = [ts[name] for name in wanted]
        ts_q_ref, ts_y_ref = getattr(ts, 'q_ref', None), getattr(ts, 'y_ref', None)
        for key in ('input_names', 'input_units', 'output_names', 'output_units'):
            names[key] = getattr(ts, key, None)
        provenance = {'training_set': str(getattr(ts, 'path', '')), 'episodes': wanted}
    else:
        eps = [data] if isinstance(data, Episode) else list(data)
        if episodes is not None:
            by_name = {ep.name: ep for ep in eps}
            missing = [e for e in episodes if e not in by_name]
            if missing:
                raise ConfigError(f'unknown episodes {missing}; have {list(by_name)}.')
            eps = [by_name[e] for e in episodes]
        provenance = {'episodes': [ep.name for ep in eps]}
    if not eps:
        raise DimensionError('no episodes to fit.')
    if t_max is not None:
        cut = []
        for ep in eps:
            k = int(np.searchsorted(ep.t - ep.t[0], float(t_max) - 1e-12, 'left'))
            if k < 2:
                raise ConfigError(f't_max={t_max} leaves fewer than 2 samples of {ep.name!r}.')
            q = None if ep.Q is None else ColumnWindow(ep.Q, k)
            cut.append(Episode(t=ep.t[:k], U=ep.U[:, :k], Y=ep.Y[:, :k], Q=q, name=ep.name,
                               metadata=dict(ep.metadata)))
        eps = cut
        provenance['t_max'] = float(t_max)
    if q_ref is None:
        q_ref = ts_q_ref
    if q_ref is None and eps[0].Q is not None:
        q_ref = np.asarray(eps[0].Q[:, 0:1], dtype=np.float64)[:, 0]
    if y_ref is None:
        y_ref = ts_y_ref if ts_y_ref is not None else eps[0].Y[:, 0]
    return TrainingData(
        episodes=eps,
        q_ref=None if q_ref is None else np.asarray(q_ref, dtype=np.float64).reshape(-1),
        y_ref=np.asarray(y_ref, dtype=np.float64).reshape(-1), names=names,
        provenance=provenance)


def make_executor(client: Any = None,
                  progress: Callable[[int], Any] | None = None) -> Executor:
    """Local executor, or a Dask one for a ``Client`` or a scheduler address string."""
    if client is None:
        return LocalExecutor(progress)
    from soft_rom.scale.dask_backend import DaskExecutor
    return DaskExecutor(client)


@dataclass
class ReducedData:
    """What the streaming pass leaves in memory: POD coordinates, inputs and outputs.

    Attributes
    ----------
    pod : StreamingPOD
        Fitted; ``pod.coords_[i]`` is ``(l, k_i)``, ``pod.reduced_[i]`` is ``(r, k_i)``.
    data : TrainingData
        Episodes (``U``, ``Y``, ``t``) and references.
    state_sq_norm_pairs : float
        :math:`\\|X_{cur}\\|_F^2` of the centred snapshots that start a pair (DMDc scaling).
    seconds : float
        Wall time of the streaming pass.
    """

    pod: StreamingPOD
    data: TrainingData
    state_sq_norm_pairs: float
    seconds: float

    @property
    def n(self) -> int:
        """Number of full-order states."""
        return int(self.pod.q_ref_.size)

    def coordinates(self, r: int) -> list[Array]:
        """:math:`V_r^T (Q_i - q_{ref})` of every episode: a list of ``(r, k_i)`` arrays."""
        return [np.ascontiguousarray(z[:r]) for z in self.pod.coords_]

    def summary(self) -> dict[str, Any]:
        """JSON-ready provenance of the streaming POD (stored in model metadata)."""
        p = self.pod
        return {
            'pod_method': p.method, 'n_coords': int(p.singular_values_.size),
            'passes': int(p.n_passes_), 'power_iters': int(p.power_iters),
            'oversample': int(p.oversample), 'seed': int(p.seed),
            'backend': type(p.executor).__name__ if p.executor is not None else 'LocalExecutor',
            'n_states': self.n, 'n_snapshots': int(sum(z.shape[1] for z in p.coords_)),
            'singular_values': p.singular_values_[:200].tolist(),
            'energy_captured_l': float(p.energy_[-1]), 'seconds': float(self.seconds),
        }


def reduce_streaming(data: Any, *, r: int | None = None, energy: float = 0.95,
                     pod: StreamingPOD | None = None, method: str = 'randomized',
                     n_coords: int | None = None, power_iters: int = 1, oversample: int = 10,
                     block_bytes: int = DEFAULT_BLOCK_BYTES, seed: int = 0,
                     client: Any = None, episodes: Sequence[str] | None = None,
                     t_max: float | None = None, q_ref: ArrayLike | None = None,
                     y_ref: ArrayLike | None = None,
                     progress: Callable[[int], Any] | None = None) -> ReducedData:
    """Stream the snapshots once through the POD; keep coordinates, inputs and outputs.

    Parameters
    ----------
    data : path, TrainingSet, TrainingData or sequence of Episode
        Episodes with full states ``Q`` (lazy zarr arrays for large sets).
    r, energy : int, float
        POD dimension, or energy fraction when ``r`` is ``None`` (paper: 0.95).
    pod : StreamingPOD, optional
        A configured (unfitted) builder; overrides the POD options below.
    method, n_coords, power_iters, oversample, block_bytes, seed
        Options of :class:`~soft_rom.scale.pod.StreamingPOD`. ``n_coords`` must be at least
        the largest ``r`` and DMDc ``p`` you will ask for.
    client : dask.distributed.Client or str, optional
        Run the passes on this Dask cluster (workers read the zarr chunks).
    episodes, t_max, q_ref, y_ref
        Selection and references (see :func:`open_training_data`).
    progress : callable, optional
        ``progress(n_columns_done)`` (local executor).

    Returns
    -------
    ReducedData
    """
    td = data if isinstance(data, TrainingData) else open_training_data(
        data, episodes=episodes, t_max=t_max, q_ref=q_ref, y_ref=y_ref)
    missing = [ep.name for ep in td.episodes if ep.Q is None]
    if missing:
        raise DimensionError(f'episodes {missing} have no full states Q: the POD needs them '
                             '(ERA/OKID does not: fit it with method="era").')
    t0 = time.perf_counter()
    if pod is None:
        pod = StreamingPOD(r=r, energy=energy, method=method, n_coords=n_coords,
                           power_iters=power_iters, oversample=oversample,
                           block_bytes=block_bytes, seed=seed,
                           executor=make_executor(client, progress), progress=progress)
    elif client is not None:
        pod.executor = make_executor(client, progress)
    snaps = SnapshotSet([ep.Q for ep in td.episodes], td.q_ref,
                        [ep.name for ep in td.episodes])
    pod.fit(snaps)
    # Squared norm of the centred snapshots that start a DMDc pair: total minus the last
    # column of each episode (E single columns, read directly).
    last = 0.0
    for ep in td.episodes:
        k = ep.Q.shape[1]
        x = np.asarray(ep.Q[:, k - 1:k], dtype=np.float64)[:, 0] - pod.q_ref_
        last += float(x @ x)
    return ReducedData(pod=pod, data=td, state_sq_norm_pairs=pod.total_energy_ - last,
                       seconds=time.perf_counter() - t0)


def _fit_lopinf(red: ReducedData, r: int, learner: Any,
                kwargs: dict[str, Any]) -> LinearROM:
    """LOpInf on the streamed coordinates: the in-memory path's ``LOpInf.fit_reduced`` call."""
    from soft_rom.learners.lopinf import LOpInf
    td, pod = red.data, red.pod
    if r > pod.singular_values_.size:
        raise ConfigError(f'r={r} exceeds the {pod.singular_values_.size} POD modes '
                          'streamed; raise n_coords.')
    est = learner if learner is not None else LOpInf(r=r, **kwargs)
    est.fit_reduced(red.coordinates(r), [ep.U for ep in td.episodes],
                    [ep.Y for ep in td.episodes], td.dt, td.y_ref,
                    names=[ep.name for ep in td.episodes],
                    energy_captured=float(np.sum(pod.singular_values_[:r] ** 2)
                                          / pod.total_energy_),
                    time_ranges=[[float(ep.t[0]), float(ep.t[-1])] for ep in td.episodes],
                    **td.model_names())
    return est.model_


def _fit_dmdc(red: ReducedData, r: int | None, p: int | None, *, energy: float = 0.95,
              rcond: float = 1e-10) -> DiscreteModel:
    """DMDc (paper sec. 2.3, scaled as :class:`~soft_rom.learners.dmdc.DMDc`) on coordinates.

    :class:`~soft_rom.learners.dmdc.DMDc` has no entry point for reduced data with the
    *full-state* RMS scale, so the SVDs are taken here and the operators built by the
    learner's own :func:`~soft_rom.learners.dmdc.dmdc_reduced_operators`.
    """
    from soft_rom.learners.dmdc import channel_scale, dmdc_reduced_operators
    td, pod = red.data, red.pod
    Zs = pod.coords_
    l = Zs[0].shape[0]
    Xc = np.concatenate([z[:, :-1] for z in Zs], axis=1)
    Xn = np.concatenate([z[:, 1:] for z in Zs], axis=1)
    Uc = np.concatenate([ep.U[:, :-1] for ep in td.episodes], axis=1)
    Z_all = np.concatenate(Zs, axis=1)
    Yd = np.concatenate([ep.Y for ep in td.episodes], axis=1) - td.y_ref[:, None]
    m = Uc.shape[0]
    # Scalar RMS of the full-order centred states (n rows), as DMDc.fit computes it.
    s_q = float(np.sqrt(red.state_sq_norm_pairs / (red.n * Xc.shape[1])))
    s_q = s_q if s_q > 0 else 1.0
    s_u = channel_scale(Uc)
    Ut, st, Vtt = np.linalg.svd(np.concatenate([Xc / s_q, Uc / s_u[:, None]]),
                                full_matrices=False)
    Uh, sh, Vht = np.linalg.svd(Xn, full_matrices=False)
    if sh.size == 0 or sh[0] <= 0:
        raise DimensionError('the states never move away from q_ref: nothing to learn.')
    rank_h = int(np.sum(sh > rcond * sh[0]))
    rank_t = int(np.sum(st > rcond * st[0]))
    if r is None:
        cum = np.cumsum(sh ** 2) / np.sum(sh ** 2)
        r = int(min(np.searchsorted(cum, energy - 1e-12) + 1, rank_h))
    r = int(r)
    if not 1 <= r <= rank_h:
        raise ConfigError(f'r must be between 1 and {rank_h} (rank of the streamed shifted '
                          f'snapshots; n_coords={l}); got {r}.')
    p_req = r + m if p is None else int(p)
    if p_req > l + m:
        raise ConfigError(f'p={p_req} exceeds n_coords + m = {l + m}; raise n_coords.')
    p_used = min(p_req, rank_t)
    G = sh[:r, None] * (Vht[:r] @ Vtt[:p_used].T)
    U1h = Ut[:l, :p_used].T @ Uh[:, :r]
    A, Bs = dmdc_reduced_operators(G, st[:p_used], U1h, Ut[l:, :p_used])
    A = A / s_q
    B = Bs / s_u[None, :]
    Xr = Uh[:, :r].T @ Z_all
    E = np.linalg.lstsq(Xr.T, Yd.T, rcond=None)[0].T
    ev = np.linalg.eigvals(A)
    meta = {
        'learner': 'DMDc', 'r': r, 'p': p_used, 'p_requested': p_req, 'output_fit': 'reduced',
        'rcond': rcond, 'episodes': [ep.name for ep in td.episodes],
        'n_pairs': int(Xc.shape[1]), 'state_scale': s_q, 'input_scale': s_u.tolist(),
        'singular_values_omega': st[:200].tolist(), 'singular_values_qp': sh[:200].tolist(),
        'energy_captured': float(np.sum(sh[:r] ** 2) / np.sum(sh ** 2)),
        'output_projection_error': relative_error(Yd, E @ Xr, if_zero=0.0),
        'eigenvalues_real': ev.real.tolist(), 'eigenvalues_imag': ev.imag.tolist(),
        'stability_margin': float(1.0 - np.max(np.abs(ev))),
    }
    return DiscreteModel(A, B, E, None, dt=td.dt, method='dmdc', y_ref=td.y_ref,
                         metadata=meta, **td.model_names())


def _fit_era(td: TrainingData, era_episode: str | None, learner: Any,
             kwargs: dict[str, Any], r: int | None) -> LinearROM:
    """ERA/OKID on one episode's inputs and outputs: the in-memory path's ``ERAOKID.fit``."""
    from soft_rom.learners.era import ERAOKID
    by_name = {ep.name: ep for ep in td.episodes}
    if era_episode is not None and era_episode not in by_name:
        raise ConfigError(f'era_episode {era_episode!r} is not among {list(by_name)}.')
    ep = by_name[era_episode] if era_episode is not None else td.episodes[0]
    io_ep = Episode(t=ep.t, U=ep.U, Y=ep.Y, Q=None, name=ep.name, metadata=dict(ep.metadata))
    est = learner if learner is not None else ERAOKID(r=r, **kwargs)
    est.fit(io_ep, td.y_ref, **td.model_names())
    return est.model_


def fit_reduced_model(reduced: ReducedData | TrainingData, method: str, r: int | None = None,
                      *, p: int | None = None, era_episode: str | None = None,
                      learner: Any = None, **learner_kwargs: Any) -> LinearROM:
    """Fit one ROM from streamed reduced data (no snapshot is read again).

    Parameters
    ----------
    reduced : ReducedData or TrainingData
        From :func:`reduce_streaming` (``TrainingData`` suffices for ``'era'``).
    method : {'lopinf', 'dmdc', 'era'}
    r : int, optional
        Reduced dimension (default: the POD's ``r_`` for LOpInf, energy rule for DMDc,
        the ERA learner's rule).
    p : int, optional
        DMDc truncation of ``Ω`` (default ``r + m``).
    era_episode : str, optional
        Episode for ERA/OKID (one episode per fit, as in the paper); default the first.
    learner : object, optional
        A configured learner to use instead of a default one: an ``LOpInf`` (its
        ``fit_reduced`` is called) or an ``ERAOKID`` (its ``fit``). ``learner_kwargs`` go to
        the default learner's constructor (to the DMDc fit: ``energy``, ``rcond``).

    Returns
    -------
    LinearROM
        With ``metadata['scale']`` (the streaming pass's :meth:`ReducedData.summary` and the
        fit's seconds).
    """
    if method not in METHODS:
        raise ConfigError(f'method must be one of {METHODS}; got {method!r}.')
    t0 = time.perf_counter()
    if method == 'era':
        td = reduced.data if isinstance(reduced, ReducedData) else reduced
        model = _fit_era(td, era_episode, learner, learner_kwargs, r)
        model.metadata.setdefault('scale', {})['fit_seconds'] = time.perf_counter() - t0
        return model
    if not isinstance(reduced, ReducedData):
        raise ConfigError(f'method {method!r} needs the streamed POD: call reduce_streaming.')
    if method == 'lopinf':
        model = _fit_lopinf(reduced, int(r) if r is not None else reduced.pod.r_, learner,
                            learner_kwargs)
    else:
        model = _fit_dmdc(reduced, r, p, **learner_kwargs)
    info = reduced.summary()
    info['fit_seconds'] = time.perf_counter() - t0
    model.metadata['scale'] = info
    return model


def fit_streaming(data: Any, method: str, r: int | None = None, *, energy: float = 0.95,
                  p: int | None = None, pod_method: str = 'randomized',
                  n_coords: int | None = None, power_iters: int = 1, oversample: int = 10,
                  block_bytes: int = DEFAULT_BLOCK_BYTES, seed: int = 0, client: Any = None,
                  episodes: Sequence[str] | None = None, t_max: float | None = None,
                  era_episode: str | None = None, q_ref: ArrayLike | None = None,
                  y_ref: ArrayLike | None = None,
                  progress: Callable[[int], Any] | None = None,
                  **learner_kwargs: Any) -> LinearROM:
    """Fit one ROM from a (possibly larger-than-memory) training set by streaming.

    Parameters
    ----------
    data : path, TrainingSet or sequence of Episode
        Training data; ``Q`` read in column blocks from disk.
    method : {'lopinf', 'dmdc', 'era'}
    r : int, optional
        Reduced dimension; for LOpInf default by ``energy`` of the POD.
    energy : float
        POD energy fraction when ``r`` is ``None`` (paper: 0.95).
    p : int, optional
        DMDc truncation of ``Ω``.
    pod_method, n_coords, power_iters, oversample, block_bytes, seed
        :class:`~soft_rom.scale.pod.StreamingPOD` options.
    client : dask.distributed.Client or str, optional
        Run the passes on a Dask cluster (``'tcp://host:8786'``).
    episodes, t_max, era_episode, q_ref, y_ref
        Data selection (see :func:`open_training_data`).
    progress : callable, optional
        ``progress(n_columns_done)``.
    **learner_kwargs
        Passed to the learner (``LOpInf``, ``ERAOKID``) or to the DMDc fit (``energy``,
        ``rcond``).

    Returns
    -------
    LinearROM
        With ``metadata['scale']`` describing the streaming pass.
    """
    td = open_training_data(data, episodes=episodes, t_max=t_max, q_ref=q_ref, y_ref=y_ref)
    if method == 'era':
        return fit_reduced_model(td, 'era', r, era_episode=era_episode, **learner_kwargs)
    if method not in METHODS:
        raise ConfigError(f'method must be one of {METHODS}; got {method!r}.')
    if n_coords is None and r is not None:
        m = td.episodes[0].U.shape[0]
        n_coords = max(int(r) + 20, 2 * int(r), (int(p) if p is not None else int(r) + m) + 10)
    red = reduce_streaming(td, r=r if method == 'lopinf' else None, energy=energy,
                           method=pod_method, n_coords=n_coords, power_iters=power_iters,
                           oversample=oversample, block_bytes=block_bytes, seed=seed,
                           client=client, progress=progress)
    return fit_reduced_model(red, method, r, p=p, **learner_kwargs)
