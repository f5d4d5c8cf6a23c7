"""Fitting ROMs over ranges of ``r`` from a training set (``soft-rom fit``, the studies).

Several ``r`` values in one call reuse the expensive part: the POD basis and projections
(LOpInf), the two SVDs (DMDc), the OKID Markov parameters (ERA). With ``streaming=True`` or a
Dask ``client`` the snapshots are streamed from disk with bounded memory
(:mod:`soft_rom.scale`) instead of being loaded.

Coordinates: LOpInf and DMDc are fitted on generalized coordinates. With ``'state'`` those
are the full states ``Q`` (POD of ``Q - q_ref``); with ``'outputs'`` (a recording of a real
robot, whose training set has no ``Q``) they are the measured outputs: ``Q := Y`` and
``q_ref := y_ref``, so that the POD runs on the output deviations. The default is
``'state'`` when every selected episode has ``Q`` and ``'outputs'`` otherwise; it is said on
stderr and recorded in the model file (``metadata['coordinates']``). Measured outputs are
noisy, so their default derivative estimator is :class:`~soft_rom.ddt.SavitzkyGolay`
(``ddt='savgol'``); states keep the eighth-order differences. The models predict outputs
from inputs either way, so the predictor, replay, evaluate and the node use them unchanged.

Mass: in output coordinates ``y = T q`` of a mechanical system the identity-mass form has a
non-symmetric stiffness, so LOpInf learns an SPD mass matrix too there (``mass='learned'``,
:mod:`soft_rom.learners.lopinf_mass`; the default on outputs, ``'identity'`` on states and
with cubic forces); said on stderr and recorded in ``metadata['mass']``.

Refinement: on measured outputs the derivatives come from noisy data, which biases the
equation-error operator fit; LOpInf then refines ``K, C, B`` by the simulation error of the
training episodes, constraints kept (``refine='output-error'``,
:mod:`soft_rom.learners.lopinf_refine`): the default on outputs with linear forces,
``'none'`` (the paper's fit) on states; said on stderr and recorded in ``metadata['refine']``.
"""

from __future__ import annotations

import sys
import time
from typing import Any

import numpy as np

from soft_rom.data import Episode
from soft_rom.envelope import training_envelope
from soft_rom.errors import ConfigError, DatasetError
from soft_rom.models import LinearROM

__all__ = ['COORDINATES', 'choose_coordinates', 'fit_models', 'fit_models_streaming',
           'select_episodes']

#: Choices of generalized coordinates for LOpInf and DMDc.
COORDINATES = ('state', 'outputs')


def select_episodes(ts: Any, names: str | list[str] | None,
                    t_max: float | None = None) -> list[Episode]:
    """Episodes ``names`` (comma-separated or list; default all), cut at ``t_max`` seconds."""
    available = list(ts.episode_names)
    if names is None:
        wanted = available
    else:
        wanted = [n.strip() for n in (names.split(',') if isinstance(names, str) else names)
                  if n.strip()]
    missing = [n for n in wanted if n not in available]
    if missing:
        raise DatasetError(f'unknown episode(s) {missing} in {getattr(ts, "path", "")}; '
                           f'available: {available}.')
    if not wanted:
        raise DatasetError('no episodes selected.')
    twice = sorted({n for n in wanted if wanted.count(n) > 1})
    if twice:
        raise DatasetError(f'episode(s) {twice} selected more than once; a repeated episode '
                           'would count double in a fit and in the pooled errors.')
    eps = [ts[n] for n in wanted]
    if t_max is not None:
        if t_max <= 0:
            raise ConfigError(f'--t-max must be positive; got {t_max}.')
        eps = [ep.time_slice(None, ep.t[0] + t_max) if ep.n_samples else ep for ep in eps]
        short = [ep.name for ep in eps if ep.n_samples < 3]
        if short:
            raise DatasetError(f'episodes {short} have fewer than 3 samples before t_max = '
                               f'{t_max} s.')
    return eps


def _names(ts: Any) -> dict[str, Any]:
    return dict(input_names=list(ts.input_names), output_names=list(ts.output_names),
                input_units=list(ts.input_units), output_units=list(ts.output_units))


def choose_coordinates(episodes: list[Episode], coordinates: str | None) -> str:
    """``'state'`` or ``'outputs'``: the choice, or the default for these episodes."""
    if coordinates is not None and coordinates not in COORDINATES:
        raise ConfigError(f'--coordinates must be one of {COORDINATES}; got {coordinates!r}.')
    if coordinates is None:
        return 'state' if all(ep.Q is not None for ep in episodes) else 'outputs'
    return coordinates


def _output_coordinates(episodes: list[Episode]) -> list[Episode]:
    """The episodes with their outputs as the coordinates (``Q := Y``)."""
    return [Episode(t=ep.t, U=ep.U, Y=ep.Y, Q=ep.Y, name=ep.name, metadata=ep.metadata)
            for ep in episodes]


def fit_models(ts: Any, method: str, *, r_values: tuple[int, ...] | None,
               energy: float | None, episodes: list[Episode], provenance: dict[str, Any],
               solver: str = 'fast', ddt_order: int = 8, dmdc_p: int | None = None,
               era_options: dict[str, Any] | None = None,
               progress: bool = True, coordinates: str | None = None,
               ddt: str | None = None, forces: str = 'linear',
               cubic_options: dict[str, Any] | None = None,
               mass: str | None = None, refine: str | None = None,
               lopinf_options: dict[str, Any] | None = None,
               dmdc_options: dict[str, Any] | None = None) -> list[tuple[LinearROM, float]]:
    """Fit ``method`` for each r; returns ``[(model, seconds), ...]``.

    ``forces`` and ``cubic_options`` are passed to :class:`~soft_rom.learners.lopinf.LOpInf`.

    The expensive step is shared between the r values (module docstring).

    Parameters
    ----------
    coordinates : {'state', 'outputs'}, optional
        Generalized coordinates of LOpInf / DMDc (default: ``'state'`` when every episode
        has ``Q``, else ``'outputs'``).
    ddt : str, optional
        LOpInf derivative estimator by name (``fd2`` .. ``fd8``, ``savgol[:W[:P]]``);
        default ``fd<ddt_order>`` on states and ``savgol`` on outputs.
    mass : {'identity', 'learned'}, optional
        LOpInf mass matrix (default ``'learned'`` on outputs with linear forces, else
        ``'identity'``).
    refine : {'none', 'output-error'}, optional
        LOpInf refinement by simulation error (default ``'output-error'`` on outputs with
        linear forces, else ``'none'``).
    """
    names = _names(ts)
    out: list[tuple[LinearROM, float]] = []
    bar = _progress(len(r_values) if r_values else 1, f'fit {method}', progress)
    q_ref = getattr(ts, 'q_ref', None)
    y_ref = ts.y_ref
    provenance = {**provenance, 't0_ns': {ep.name: int(ep.metadata.get('t0_ns', 0))
                                          for ep in episodes}}
    coords = 'state'
    if method in ('lopinf', 'dmdc'):
        coords = choose_coordinates(episodes, coordinates)
        if coords == 'outputs':
            episodes = _output_coordinates(episodes)
            q_ref = y_ref
    if ddt is None:
        ddt = 'savgol' if coords == 'outputs' else f'fd{ddt_order}'
    if mass is None:
        mass = 'learned' if coords == 'outputs' and forces == 'linear' else 'identity'
    if mass not in ('identity', 'learned'):
        raise ConfigError(f"--mass must be 'identity' or 'learned'; got {mass!r}.")
    if refine is None:
        refine = 'output-error' if coords == 'outputs' and forces == 'linear' else 'none'
    if refine not in ('none', 'output-error') or (refine != 'none' and forces != 'linear'):
        raise ConfigError(f"--refine must be 'none' or 'output-error' (linear forces only); "
                          f'got {refine!r} with --forces {forces}.')
    if coords == 'outputs':
        why = ' (the training set has no Q)' if coordinates is None else ''
        how = (f', derivatives by {ddt}, {mass} mass'
               + (', refined by output error' if refine != 'none' else '')
               if method == 'lopinf' else '')
        print(f'note: {method} uses the measured outputs (deviations from y_ref) as its '
              f'coordinates{why}{how}; --coordinates to choose.', file=sys.stderr)
    elif method == 'lopinf' and mass == 'learned':
        print('note: lopinf learns an SPD mass matrix (--mass learned).', file=sys.stderr)
    from soft_rom.ddt import parse_estimator
    estimator = parse_estimator(ddt)
    extra = {'coordinates': coords}
    try:
        if method == 'lopinf':
            from soft_rom.basis import POD, project
            from soft_rom.learners.lopinf import LOpInf
            from soft_rom.learners.lopinf_solvers import CvxpySolver, FastSPDSolver
            _need_states(episodes, 'LOpInf')
            t0 = time.perf_counter()
            q_ref = _q_ref(q_ref, episodes)
            r_max = max(r_values) if r_values else None
            pod = POD(r=r_max, energy=0.95 if energy is None else energy).fit(
                [ep.Q for ep in episodes], q_ref)
            Qhat = [project(ep.Q, pod.basis_, q_ref) for ep in episodes]
            t_basis = time.perf_counter() - t0
            dt = episodes[0].dt
            slv = FastSPDSolver() if solver == 'fast' else CvxpySolver()
            r_fit = r_max or pod.r_
            learner = LOpInf(r=r_fit, ddt=estimator, solver=slv, forces=forces,
                             cubic_options=cubic_options, mass=mass, refine=refine,
                             **(lopinf_options or {}))
            learner.fit_reduced(
                [q[:r_fit] for q in Qhat], [ep.U for ep in episodes],
                [ep.Y for ep in episodes], dt, y_ref, names=[ep.name for ep in episodes],
                energy_captured=float(pod.energy_[r_fit - 1]),
                time_ranges=[[float(ep.t[0]), float(ep.t[-1])] for ep in episodes],
                metadata={'training': provenance, **extra,
                          'pod_singular_values': pod.singular_values_[:100].tolist()},
                **names)
            t_fit = time.perf_counter() - t0 - t_basis
            ref = learner.diagnostics_.get('refinement')
            if isinstance(ref, dict) and ref.get('status') == 'skipped_too_large':
                print(f'note: lopinf r = {r_fit}: the output-error refinement is too large '
                      'to run here and was skipped (the model is the equation-error fit).',
                      file=sys.stderr)
            for r in (r_values or (pod.r_,)):
                t1 = time.perf_counter()
                model = learner.model_for(r, energy_captured=float(pod.energy_[r - 1]))
                seconds = t_fit if r == r_fit else time.perf_counter() - t1
                out.append((model, t_basis / len(r_values or (1,)) + seconds))
                bar.update(1)
        elif method == 'dmdc':
            from soft_rom.learners.dmdc import DMDc
            _need_states(episodes, 'DMDc')
            t0 = time.perf_counter()
            r0 = r_values[0] if r_values else None
            dmdc = DMDc(r=r0, p=dmdc_p, energy=0.95 if energy is None else energy,
                        **(dmdc_options or {})).fit(
                episodes, _q_ref(q_ref, episodes), y_ref,
                metadata={'training': provenance, **extra}, **names)
            t_svd = time.perf_counter() - t0
            r_opt: int | None
            for r_opt in (r_values or (None,)):
                t1 = time.perf_counter()
                model = (dmdc.model_ if r_opt is None or r_opt == r0
                         else dmdc.model_for(r_opt, dmdc_p))
                model.metadata.update(extra)
                out.append((model, t_svd / len(r_values or (1,)) + time.perf_counter() - t1))
                bar.update(1)
        elif method == 'era':
            from soft_rom.learners.era import ERAOKID
            opts = {k: v for k, v in (era_options or {}).items() if v is not None}
            ep_name = opts.pop('episode', None)
            if ep_name is None:
                ep = episodes[0]
                if len(episodes) > 1:
                    print(f'note: ERA/OKID fits one episode; using {ep.name!r} '
                          '(choose with --era-episode).', file=sys.stderr)
            else:
                match = [e for e in episodes if e.name == ep_name]
                if not match:
                    raise DatasetError(f'--era-episode {ep_name!r} is not among the selected '
                                       f'episodes {[e.name for e in episodes]}.')
                ep = match[0]
            t0 = time.perf_counter()
            r0 = r_values[0] if r_values else None
            era = ERAOKID(r=r0, **opts).fit(
                ep, y_ref, metadata={'training': {**provenance, 'episodes': [ep.name]}},
                **names)
            t_okid = time.perf_counter() - t0
            for r_opt in (r_values or (None,)):
                t1 = time.perf_counter()
                model = era.model_ if r_opt is None or r_opt == r0 else era.model_for(r_opt)
                out.append((model, t_okid / len(r_values or (1,)) + time.perf_counter() - t1))
                bar.update(1)
        else:  # pragma: no cover - argparse restricts the choices
            raise ConfigError(f'unknown method {method!r}.')
    finally:
        bar.close()
    for fitted, _ in out:
        _record_layout(fitted, ts)
    return out


def _record_layout(model: LinearROM, ts: Any) -> None:
    """Carry the training set's output layout into the model's metadata."""
    layout = getattr(ts, 'output_layout', None)
    if layout is not None:
        model.metadata['output_layout'] = layout.to_dict()


def _need_states(episodes: list[Episode], what: str) -> None:
    missing = [ep.name for ep in episodes if ep.Q is None]
    if missing:
        raise DatasetError(f'{what} with --coordinates state needs full states Q but episodes '
                           f'{missing} have none (converted with --no-state?); use '
                           '--coordinates outputs (the default without Q).')


def _q_ref(q_ref: Any, episodes: list[Episode]) -> np.ndarray:
    if q_ref is not None:
        return np.asarray(q_ref, dtype=np.float64)
    return np.asarray(episodes[0].Q[:, 0:1], dtype=np.float64)[:, 0]


class _NoBar:
    def update(self, n: int = 1) -> None:
        pass

    def close(self) -> None:
        pass


def _progress(total: int, desc: str, enabled: bool) -> Any:
    if not enabled or total <= 1:
        return _NoBar()
    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover
        return _NoBar()
    return tqdm(total=total, desc=desc, unit='model', file=sys.stderr, leave=False)


def fit_models_streaming(ts: Any, method: str, *, r_values: tuple[int, ...] | None,
                         energy: float | None, episodes: list[str] | None,
                         t_max: float | None, provenance: dict[str, Any],
                         dmdc_p: int | None = None, era_options: dict[str, Any] | None = None,
                         client: Any = None, progress: bool = True, mass: str | None = None,
                         refine: str | None = None) -> list[tuple[LinearROM, float]]:
    """Like :func:`fit_models`, streaming the snapshots from disk (or on a Dask cluster).

    One streamed POD pass (:func:`soft_rom.scale.streaming.reduce_streaming`) serves every ``r``;
    ``client`` is a ``dask.distributed.Client`` or a scheduler address.
    """
    if method in ('lopinf', 'dmdc') and getattr(ts, 'q_ref', None) is None:
        # no Q: the outputs are the coordinates, small enough to fit in memory
        eps = select_episodes(ts, episodes, t_max)
        return fit_models(ts, method, r_values=r_values, energy=energy, episodes=eps,
                          provenance=provenance, dmdc_p=dmdc_p, era_options=era_options,
                          progress=progress, mass=mass, refine=refine)
    if mass == 'learned' and method == 'lopinf':
        raise ConfigError('--mass learned on states is fitted in memory; drop --streaming/--dask')
    if refine not in (None, 'none') and method == 'lopinf':
        raise ConfigError('--refine output-error on states is fitted in memory; drop '
                          '--streaming/--dask')
    opts = {k: v for k, v in (era_options or {}).items() if v is not None}
    era_episode = opts.pop('episode', None)
    own_client = isinstance(client, str)
    if own_client:
        from soft_rom.scale.dask_backend import connect
        client = connect(client)
    try:
        return _fit_streaming(ts, method, r_values, energy, episodes, t_max, provenance,
                              dmdc_p, opts, era_episode, client)
    finally:
        if own_client:
            client.close()


def _fit_streaming(ts: Any, method: str, r_values: tuple[int, ...] | None,
                   energy: float | None, episodes: list[str] | None, t_max: float | None,
                   provenance: dict[str, Any], dmdc_p: int | None, opts: dict[str, Any],
                   era_episode: str | None, client: Any) -> list[tuple[LinearROM, float]]:
    from soft_rom.scale.streaming import fit_reduced_model, reduce_streaming
    t0 = time.perf_counter()
    red = None
    if method in ('lopinf', 'dmdc'):
        r_max = max(r_values) if r_values else None
        n_coords = None
        if r_max is not None:
            n_coords = max(r_max, (dmdc_p or r_max + len(ts.input_names))) + 10
        red = reduce_streaming(ts, r=r_max, energy=0.95 if energy is None else energy,
                               n_coords=n_coords, client=client, episodes=episodes,
                               t_max=t_max)
    t_pass = time.perf_counter() - t0
    out: list[tuple[LinearROM, float]] = []
    envelope = training_envelope(select_episodes(ts, episodes, t_max), ts.y_ref)
    for r in (r_values or (None,)):
        t1 = time.perf_counter()
        if method == 'era':  # inputs and outputs only: nothing to stream
            eps = select_episodes(ts, episodes, t_max)
            model = fit_models(ts, 'era', r_values=(r,) if r else None, energy=energy,
                               episodes=eps, provenance=provenance,
                               era_options={**opts, 'episode': era_episode},
                               progress=False)[0][0]
        else:
            kw: dict[str, Any] = {'p': dmdc_p} if method == 'dmdc' else {}
            if red is None:  # pragma: no cover - set above for lopinf and dmdc
                raise ConfigError(f'unknown method {method!r}.')
            model = fit_reduced_model(red, method, r, **kw)
        model.metadata.setdefault('training', provenance)
        model.metadata.setdefault('envelope', envelope)
        _record_layout(model, ts)
        out.append((model, t_pass / len(r_values or (1,)) + time.perf_counter() - t1))
    return out
