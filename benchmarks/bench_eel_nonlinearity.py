"""Diagnostic: what kind of nonlinearity separates the eel FOM from every linear ROM.

Measurements on the study's default eel (mesh resolution 1, 50 kPa antagonistic
random pressures, 1 ms):

1. **Amplitude scan.** Test episode Ep 3's pressures scaled by ``s``, simulated with the
   nonlinear FOM and with its linearization about rest (``EelModel.simulate(linear=True)``):
   relative distance of the centerline deviations ``|Y_lin - Y| / |Y - y_ref|`` (``x`` and
   ``z`` of the 20 points, as the study's outputs), and the exponent ``p`` of
   ``distance ∝ s^p`` between neighbouring amplitudes. ``p ≈ 2`` means a smooth polynomial
   nonlinearity whose lowest term is cubic in the displacements (a quadratic one would give
   ``p ≈ 1``).
2. **Follower loads.** The same episode at ``s = 1`` with dead pressure loads
   (``follower=False``, a constant ``B``) against the default follower loads: how much of the
   nonlinearity a configuration-dependent input matrix carries.
3. **Which terms explain the linear ROM's equation residual.** The study's linear LOpInf
   (``r`` reduced coordinates, trained on Ep 1 + Ep 2) leaves the acceleration residual
   ``q̈ + C q̇ + K q - B u`` (8th-order differences of the projected FEM states). Each family
   of candidate terms is regressed on it (ridge, the weight best on the test episodes, so an
   upper bound of what the family can explain), after a zero-phase low-pass filter applied
   to both sides (``--cutoff`` Hz; filtering commutes with the linear regression), and the
   fraction of the residual explained (R²) on the training and on the test episodes
   (Ep 3 - 6) is printed. Families: ``q²`` and ``q³`` (the gradients of a cubic and a
   quartic potential, what ``forces='cubic'`` adds), ``u²`` (an input nonlinearity; even
   terms matter because the discrete eel is not mirror-symmetric, section 4), ``u q`` and
   ``u q²`` (a configuration-dependent input matrix),
   ``u² q`` (a pressure-dependent stiffness), ``u³``, and velocity terms.
4. **Is the discrete eel mirror-symmetric?** The body and its chambers are symmetric about
   ``z = 0``, and an antagonistic pair driven with ``-u`` is the mirror image of ``+u``, so a
   symmetric model would bend the tail by exactly opposite amounts and its potential would
   be even (``G = 0``). Printed: how many tetrahedra of the mesh map onto tetrahedra under
   ``z → -z``, and the static tail deflection (8 s at 5 ms steps, pressures ramped over 1 s)
   under ``±50 kPa`` on the last segment's pair, nonlinear and linearized.

5. **Do the equations generalize from Ep 1 + Ep 2 at all?** Unconstrained least squares
   of ``q̈`` on ``[q, q̇, u]`` (a linear second-order model, no SPD constraint), and on the same
   plus the ``q³`` monomials (all ``r`` coordinates, or only the first two), at several ``r``
   (``--gen-r``), low-passed like 3., ridge weight best on the test episodes: the relative
   equation error on the training and on the test episodes. A linear model that fits the
   training equations to 1 % and misses the test ones by 40 % says that two episodes do not
   pin down even the linear operators at the equation level, before any nonlinear term.

6. **How much of the linear ROM's test error is representation?** (``--projection TRAIN
   TEST``, two training sets written by ``soft-rom study --learning-curve``, e.g. its
   ``data/50kPa_train.zarr`` and ``data/50kPa_test.zarr``; only this check runs then.) The
   POD of the first ``--projection-n`` training episodes (as the learning curve builds it),
   and the output error of the test episodes' FEM states represented in it, relative to
   their deviations: linearly (``C V Vᵀ x``), and on a quadratic manifold
   (``C (V q + W (q ⊗ q))``, ``q = Vᵀ x``, ``C W`` fitted by ridge least squares to the
   training states' residual outputs, the decoder of Geelen, Wright & Willcox 2023 that is
   the usual remedy for geometric nonlinearity). No dynamics: what is left of a ROM's error
   above these figures is in its reduced dynamics.

7. **Do cubic reduced dynamics pay off, given the right coefficients?** (``--dynamics``, with
   ``--projection``: on the same POD, at ``--projection-r``.) The test episodes are run
   through three reduced models in the FOM's own scheme (semi-implicit Euler, the rest
   stiffness and the Rayleigh damping implicit, 1 ms): the intrusive Galerkin ROM (the
   corotational forces of ``x = q_ref + V q``, follower pressure loads); the same with the
   elastic force replaced by a cubic polynomial in ``q`` fitted by least squares to the exact
   reduced forces at every 10th projected training state (an upper bound of what a cubic
   LOpInf could learn; follower and dead loads); and, from trajectories only, an
   unconstrained equation-error fit of ``q̈`` on ``[q, cubic(q), q̇, u]`` (finite differences
   of the projected training states, ridge 1e-8).

8. **Are the projected trajectories Markovian?** (``--closure``, with ``--projection``.) A
   fit from trajectories sees the reduced force of the *true* state, ``Vᵀ f(x)``; a reduced
   model can only know ``Vᵀ f(q_ref + V q)``, ``q = Vᵀ (x - q_ref)``. Their relative
   difference over every 40th training state, for the corotational elastic force and for
   its linear part (the rest stiffness), is the closure error the learned operators must
   absorb (re-projection, Peherstorfer 2020, is the known remedy).

9. **Re-projection.** (``--reproject``, with ``--projection``.) Every 10th training state
   and its velocity are projected M-orthogonally onto the POD subspace (coordinates ``z``
   with ``Wᵀ M W = I``, so the reduced elastic force is a gradient and the mass the
   identity, as the cubic LOpInf assumes), and the FOM's right-hand side is evaluated there
   (corotational forces, follower pressure loads, Rayleigh damping): Markovian triples
   ``(z, ż, z̈)``. The cubic LOpInf's least squares (``soft_rom.learners.lopinf.cubic``, the
   quartic potential, ``reg`` 0 and 1e-8, no constraints) and the linear LOpInf's SPD solve are
   fitted to them and compared with the linear LOpInf fitted to the training trajectories.
   The linear model runs with its stiffness and damping implicit (1 ms); the cubic one is
   the library's ``CubicSecondOrderModel`` (its energy-consistent implicit step), run on
   the test inputs and on inputs 10 × longer than a training episode (the test inputs
   chained, as the learning curve's bounded check builds them), with the fraction of random
   directions in which its quartic is negative. ``--reproject-scale 1.5 2`` also
   re-projects the states scaled by those factors (states beyond the training data).
   ``--reproject-sos`` adds the certified variant: ``K`` and ``C`` of the least squares kept,
   the quartic moved to the nearest sum of squares in the data's metric (SCS), ``G`` and
   ``B`` refitted: the library's ``fit_cubic(..., quartic='projected')``.
10. ``--reproject-select``: the r of that certified model chosen among ``--projection-r`` on
   held-out training episodes (4 interleaved folds, as the library's selection), beside
   the linear LOpInf of the trajectories on the same folds; the chosen r is then fitted on
   all training episodes and run on the test episodes (used once, after the choice).

The reduced episodes come from ``--data`` (default ``/tmp/cubic_cache/eel_reduced.npz``,
made by ``bench_cubic_eel.py`` with the study's pipeline when missing; never inside the
repository). The FEM runs take about 45 s.

Run::

    .venv/bin/python benchmarks/bench_eel_nonlinearity.py [--r 6] [--cutoff 5]
        [--gen-r 4 8 22] [--only-gen]
    .venv/bin/python benchmarks/bench_eel_nonlinearity.py --projection TRAIN.zarr TEST.zarr
        [--projection-n 16] [--projection-r 4 6 8 12 16] [--dynamics] [--closure] [--reproject]
        [--reproject-scale 1.5 2] [--reproject-sos] [--reproject-select]

Figures of one run are quoted in docs/methods_variants.md (cubic LOpInf section).
"""

from __future__ import annotations

import argparse
import functools
from itertools import combinations_with_replacement
import math
from pathlib import Path
import sys
import time
from typing import Any

import numpy as np
import scipy.signal as ss

from soft_rom.ddt import FiniteDifference
from soft_rom.metrics import relative_deviation_error
from soft_rom.sim.eel import EelModel

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_cubic_eel as bce  # noqa: E402

FAMILIES = ('linear', 'q2', 'q3', 'u2', 'uq', 'uq2', 'u2q', 'u3', 'q2v', 'v3')


def _outputs(result: object) -> np.ndarray:
    """``x1..x20, z1..z20`` rows of a simulation's centerline (the study's outputs)."""
    c = np.asarray(result.centerline)              # type: ignore[attr-defined]
    return np.concatenate([c[:, 0], c[:, 2]], axis=0)


def amplitude_scan(U: np.ndarray, scales: tuple[float, ...]) -> None:
    model, dead = EelModel(), EelModel(follower=False)
    n = U.shape[1]
    print('1. FOM against its linearization, Ep 3 pressures scaled by s')
    prev: tuple[float, float] | None = None
    for s in scales:
        Y = _outputs(model.simulate(U * s, n, 1e-3))
        Yl = _outputs(model.simulate(U * s, n, 1e-3, linear=True))
        ref = Y[:, 0]
        d = relative_deviation_error(Y, Yl, ref)
        peak = float(np.max(np.abs(Y - ref[:, None])))
        peak_l = float(np.max(np.abs(Yl - ref[:, None])))
        slope = '' if prev is None else \
            f', exponent p = {np.log(prev[1] / d) / np.log(prev[0] / s):.2f}'
        print(f'   s = {s:5.2f}: |Y_lin - Y| / |Y - y_ref| = {d:.4f}; peak deviation '
              f'{peak * 1e3:.2f} mm (linearization {peak_l * 1e3:.2f} mm){slope}')
        prev = (s, d)
    Y = _outputs(model.simulate(U, n, 1e-3))
    Yd = _outputs(dead.simulate(U, n, 1e-3))
    Yl = _outputs(model.simulate(U, n, 1e-3, linear=True))
    ref = Y[:, 0]
    print('2. Follower against dead pressure loads, s = 1: '
          f'|Y_dead - Y| / |Y - y_ref| = {relative_deviation_error(Y, Yd, ref):.4f} '
          f'(linearization: {relative_deviation_error(Y, Yl, ref):.4f})')


@functools.lru_cache(maxsize=None)
def _combinations(n: int, degree: int) -> np.ndarray:
    return np.array(list(combinations_with_replacement(range(n), degree)), dtype=np.intp).T


def _monomials(X: np.ndarray, degree: int) -> np.ndarray:
    """The distinct products of ``degree`` rows of ``X`` (i <= j <= ...), per column."""
    return np.prod(X[_combinations(X.shape[0], degree)], axis=0)


def residual_families(data: bce.Data, cutoff: float) -> None:
    lin = data.linear()
    m = lin.model_
    b, a = ss.butter(4, cutoff, fs=1.0 / data.dt)

    def prep(eps: tuple[int, ...]) -> tuple[list[np.ndarray], ...]:
        Q, Qd, Qdd, (U,) = FiniteDifference(order=8).episodes(
            [data.Q[i] for i in eps], data.dt, [[data.U[i] for i in eps]])
        Q, Qd, Qdd, U = ([x] if isinstance(x, np.ndarray) else list(x)
                         for x in (Q, Qd, Qdd, U))
        R = [qdd + m.C @ qd + m.K @ q - m.B @ u for q, qd, qdd, u in zip(Q, Qd, Qdd, U)]
        return Q, Qd, [u[0::2] for u in U], R     # antagonistic pairs: one drive per segment

    tr, te = prep(bce.TRAIN), prep(bce.TESTS)
    cat = np.concatenate
    qs = np.sqrt(np.mean(cat(tr[0], axis=1) ** 2, axis=1))[:, None]
    vs = np.sqrt(np.mean(cat(tr[1], axis=1) ** 2, axis=1))[:, None]
    us = np.sqrt(np.mean(cat(tr[2], axis=1) ** 2, axis=1))[:, None]

    def features(q: np.ndarray, v: np.ndarray, u: np.ndarray, fam: str) -> np.ndarray:
        q, v, u = q / qs, v / vs, u / us
        if fam == 'linear':
            return np.vstack([q, v, u])
        if fam == 'q2':
            return _monomials(q, 2)
        if fam == 'q3':
            return _monomials(q, 3)
        if fam == 'u2':
            return _monomials(u, 2)
        if fam == 'uq':
            return np.array([uk * qi for uk in u for qi in q])
        if fam == 'uq2':
            return np.array([uk * p for uk in u for p in _monomials(q, 2)])
        if fam == 'u2q':
            return np.array([p * qi for p in _monomials(u, 2) for qi in q])
        if fam == 'u3':
            return _monomials(u, 3)
        if fam == 'q2v':
            return np.array([p * vi for p in _monomials(q, 2) for vi in v])
        return _monomials(v, 3)

    def stacked(parts: tuple[list[np.ndarray], ...], fam: str) -> tuple[np.ndarray, np.ndarray]:
        F = [ss.filtfilt(b, a, features(q, v, u, fam), axis=1)
             for q, v, u, _ in zip(*parts)]
        R = [ss.filtfilt(b, a, r_, axis=1) for r_ in parts[3]]
        return cat(F, axis=1), cat(R, axis=1)

    print(f'3. Linear LOpInf (r = {data.r}) equation residual, low-passed at {cutoff:g} Hz: '
          'fraction explained by each family (ridge weight best on the test episodes)')
    for fam in FAMILIES:
        Ftr, Rtr = stacked(tr, fam)
        Fte, Rte = stacked(te, fam)
        G, g = Ftr @ Ftr.T, Ftr @ Rtr.T
        best = (-np.inf, 0.0, 0.0)
        for lam in (1e-6, 1e-4, 1e-2, 1.0, 1e2):
            W = np.linalg.solve(G + lam * np.trace(G) / len(G) * np.eye(len(G)), g)
            r2_te = 1 - np.sum((Rte - W.T @ Fte) ** 2) / np.sum(Rte ** 2)
            r2_tr = 1 - np.sum((Rtr - W.T @ Ftr) ** 2) / np.sum(Rtr ** 2)
            if r2_te > best[0]:
                best = (r2_te, r2_tr, lam)
        print(f'   {fam:7s} {Ftr.shape[0]:4d} terms: R² train {best[1]:.3f}, test {best[0]:.3f} '
              f'(ridge {best[2]:g})')


def _derivatives(data: bce.Data, eps: tuple[int, ...]) -> list[list[np.ndarray]]:
    """``[Q, Q̇, Q̈, U]`` of the episodes ``eps``, one array per episode in each list."""
    Q, Qd, Qdd, (U,) = FiniteDifference(order=8).episodes(
        [data.Q[i] for i in eps], data.dt, [[data.U[i] for i in eps]])
    return [[x] if isinstance(x, np.ndarray) else list(x) for x in (Q, Qd, Qdd, U)]


def _equation_rows(parts: list[list[np.ndarray]], nl: int, scale: list[np.ndarray],
                   ba: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Low-passed regressors ``[q, q̇, u, (q³ of the first nl)]`` and accelerations."""
    F, A = [], []
    for q, v, acc, u in zip(*parts):
        rows = [q / scale[0], v / scale[1], u[0::2] / scale[2][0::2]]
        if nl:
            rows.append(_monomials(q[:nl] / scale[0][:nl], 3))
        F.append(ss.filtfilt(*ba, np.vstack(rows), axis=1))
        A.append(ss.filtfilt(*ba, acc, axis=1))
    return np.concatenate(F, axis=1), np.concatenate(A, axis=1)


def equation_generalization(path: Path, rs: tuple[int, ...], cutoff: float) -> None:
    """Unconstrained equation-error fits on Ep 1 + Ep 2, scored on Ep 3 - 6 (5)."""
    print(f'5. Unconstrained equation-error fits (low-passed at {cutoff:g} Hz): relative '
          'equation error, train / test')
    for r in rs:
        data = bce.Data(path, r)
        ba = ss.butter(4, cutoff, fs=1.0 / data.dt)
        tr, te = _derivatives(data, bce.TRAIN), _derivatives(data, bce.TESTS)
        scale = [np.sqrt(np.mean(np.concatenate(tr[k], axis=1) ** 2, axis=1))[:, None]
                 for k in (0, 1, 3)]
        for label, nl in (('linear', 0), ('+ q³ of q1, q2', 2), (f'+ q³ of all {r}', r)):
            Ftr, Atr = _equation_rows(tr, nl, scale, ba)
            Fte, Ate = _equation_rows(te, nl, scale, ba)
            G, g = Ftr @ Ftr.T, Ftr @ Atr.T
            best = (np.inf, np.inf)
            for lam in (1e-10, 1e-8, 1e-6, 1e-4):
                W = np.linalg.solve(G + lam * np.trace(G) / len(G) * np.eye(len(G)), g)
                e_te = float(np.linalg.norm(Ate - W.T @ Fte) / np.linalg.norm(Ate))
                e_tr = float(np.linalg.norm(Atr - W.T @ Ftr) / np.linalg.norm(Atr))
                best = min(best, (e_te, e_tr))
            print(f'   r = {r:2d} {label:16s} {Ftr.shape[0]:4d} terms: train {best[1]:.4f}, '
                  f'test {best[0]:.4f}', flush=True)


def mirror_check(amplitude: float = 50e3) -> None:
    """Mesh symmetry under ``z -> -z`` and the static tail deflection under ``±u`` (4)."""
    model = EelModel()
    X, T = model.mesh.nodes, model.mesh.tets
    index = {tuple(np.round(x, 9)): i for i, x in enumerate(X)}
    mirror = np.array([index.get(tuple(np.round(x * (1.0, 1.0, -1.0), 9)), -1) for x in X])
    tets = {tuple(sorted(t)) for t in T}
    mapped = sum(tuple(sorted(mirror[t])) in tets for t in T) if np.all(mirror >= 0) else 0
    print(f'4. Mirror symmetry z -> -z: nodes {"symmetric" if np.all(mirror >= 0) else "NOT"}; '
          f'{mapped} of {len(T)} tetrahedra map onto tetrahedra')
    dt, n = 5e-3, 1600
    ramp = np.clip(np.arange(n) * dt / 1.0, 0.0, 1.0)
    pair = np.zeros(model.n_chambers)
    pair[-2:] = (1.0, -1.0)
    for sign in (1.0, -1.0):
        U = np.outer(sign * amplitude * pair, ramp)
        tip = []
        for linear in (False, True):
            Y = model.simulate(U, n, dt, linear=linear).outputs()
            tip.append(1e3 * (Y[-1, -1] - Y[-1, 0]))
        print(f'   {sign * amplitude / 1e3:+.0f} kPa on the last pair: static tail-tip z '
              f'{tip[0]:+.2f} mm (linearized {tip[1]:+.2f} mm)', flush=True)


def representation(train_path: Path, test_path: Path, n_train: int,
                   rs: tuple[int, ...], dynamics: bool = False, closure: bool = False,
                   reproject: bool = False, scales: tuple[float, ...] = (),
                   sos: bool = False, select: bool = False) -> None:
    """Output error of the test states in a linear POD and on a quadratic manifold (6)."""
    from soft_rom.basis import POD
    from soft_rom.dataset.reader import TrainingSet
    train, test = TrainingSet.open(train_path), TrainingSet.open(test_path)
    eps = train.episodes(train.episode_names[:n_train])
    q_ref, y_ref = np.asarray(train.q_ref), np.asarray(train.y_ref)
    C = EelModel().output_matrix('xz')
    X = np.concatenate([np.asarray(ep.Q[:, :]) - q_ref[:, None] for ep in eps], axis=1)
    V_all = POD(r=max(rs)).fit([ep.Q for ep in eps], q_ref).basis_
    tests = [(np.asarray(ep.Q[:, :]) - q_ref[:, None], np.asarray(ep.Y) - y_ref[:, None])
             for ep in test]
    mismatch = max(float(np.abs(C @ x - y).max()) for x, y in tests)
    print(f'6. Representation error of the {len(tests)} test episodes, POD of {len(eps)} '
          f'training episodes (|C x - y| at most {mismatch:.1e} m), relative to the '
          'deviations:')
    for r in rs:
        V = V_all[:, :r]
        q = V.T @ X
        K, R = _monomials(q, 2), C @ (X - V @ q)                 # products, residual outputs
        lam = 1e-6 * np.trace(K @ K.T) / len(K)
        W = np.linalg.solve(K @ K.T + lam * np.eye(len(K)), K @ R.T).T
        lin, quad = [], []
        for x, y in tests:
            qt = V.T @ x
            y_lin = C @ (V @ qt)
            lin.append(np.linalg.norm(y_lin - y) / np.linalg.norm(y))
            quad.append(np.linalg.norm(y_lin + W @ _monomials(qt, 2) - y) / np.linalg.norm(y))
        print(f'   r = {r:2d} linear POD ' + ' / '.join(f'{v:.3f}' for v in lin)
              + '; quadratic manifold ' + ' / '.join(f'{v:.3f}' for v in quad), flush=True)
    if dynamics:
        reduced_dynamics(eps, list(test), V_all, q_ref, rs)
    if closure:
        closure_error(X[:, ::40], V_all, q_ref, rs)
    if reproject:
        reprojection(eps, list(test), V_all, train, rs, scales, sos)
    if select:
        reprojected_selection(eps, list(test), V_all, train, rs)


def closure_error(X: np.ndarray, V_all: np.ndarray, q_ref: np.ndarray, rs: tuple[int, ...]
                  ) -> None:
    """``|Vᵀ f(x) - Vᵀ f(q_ref + V Vᵀ x)| / |Vᵀ f(x)|`` over the states ``X`` (8)."""
    model = EelModel()
    free, K0 = model.free, model._rest_factor(1e-3)[1]

    def forces(D: np.ndarray) -> np.ndarray:                   # elastic force, free DOFs
        return np.stack([model.fem.elastic_force((q_ref + d).reshape(-1, 3)).ravel()[free]
                         for d in D.T], axis=1)

    F = forces(X)
    print(f'8. Closure error over {X.shape[1]} training states (reduced force of the true '
          'state against that of its projection):')
    for r in rs:
        V = V_all[:, :r]
        P = V @ (V.T @ X)
        Vf = V[free]
        a, b = Vf.T @ F, Vf.T @ forces(P)
        al, bl = Vf.T @ (K0 @ X[free]), Vf.T @ (K0 @ P[free])
        print(f'   r = {r:2d} elastic force {np.linalg.norm(a - b) / np.linalg.norm(a):.3f}, '
              f'its linear part {np.linalg.norm(al - bl) / np.linalg.norm(al):.3f}', flush=True)


def _monomials_up_to_3(q: np.ndarray) -> np.ndarray:
    """``q``, its distinct products of two and of three factors (rows), per column."""
    return np.concatenate([q, _monomials(q, 2), _monomials(q, 3)], axis=0)


class _Reduced:
    """The FOM's time step on ``x = q_ref + V q`` (check 7)."""

    def __init__(self, model: EelModel, V: np.ndarray, q_ref: np.ndarray, h: float = 1e-3):
        cfg = model.config
        _, K0, m = model._rest_factor(h)
        self.model, self.V, self.q_ref, self.h = model, V, q_ref, h
        self.Vf = V[model.free]
        A = (self.Vf.T @ (m[:, None] * (1 + h * cfg.rayleigh_mass) * self.Vf)
             + (h * cfg.rayleigh_stiffness + h * h) * (self.Vf.T @ (K0 @ self.Vf)))
        self.Ai, self.M = np.linalg.inv(A), self.Vf.T @ (m[:, None] * self.Vf)
        self.B = self.Vf.T @ np.asarray(model.B.todense())[model.free]

    def x(self, q: np.ndarray) -> np.ndarray:
        return (self.q_ref + self.V @ q).reshape(-1, 3)

    def elastic(self, q: np.ndarray) -> np.ndarray:
        return self.Vf.T @ self.model.fem.elastic_force(self.x(q)).ravel()[self.model.free]

    def follower(self, q: np.ndarray, u: np.ndarray) -> np.ndarray:
        return self.Vf.T @ self.model.pressure_force(self.x(q), u).ravel()[self.model.free]

    def run(self, U: np.ndarray, C: Any, force: Any) -> np.ndarray:
        r = self.V.shape[1]
        q, qd = np.zeros(r), np.zeros(r)
        Y = np.full((C.shape[0], U.shape[1]), np.nan)
        with np.errstate(over='ignore', invalid='ignore'):        # a blow-up ends the run
            for j in range(U.shape[1]):
                Y[:, j] = C @ (self.q_ref + self.V @ q)
                qd = self.Ai @ (self.M @ qd + self.h * force(q, U[:, j]))
                q = q + self.h * qd
                if not np.all(np.isfinite(q)):
                    break
        return Y


class _EquationErrorCubic:
    """Unconstrained least squares of ``q̈`` on ``[q, cubic(q), q̇, u]`` (check 7)."""

    def __init__(self, Qs: list[np.ndarray], Us: list[np.ndarray], h: float) -> None:
        s = np.concatenate(Qs, axis=1).std(axis=1)
        rows, acc = [], []
        for q, u in zip(Qs, Us):
            v = np.diff(q, axis=1) / h                   # v[:, j]: velocity after step j
            rows.append(np.concatenate([_monomials_up_to_3(q[:, 1:-1] / s[:, None]),
                                        v[:, :-1] / s[:, None], u[:, 1:-1] / 1e4]))
            acc.append(np.diff(v, axis=1) / h)
        Phi, A = np.concatenate(rows, axis=1), np.concatenate(acc, axis=1)
        G = Phi @ Phi.T
        W = np.linalg.solve(G + 1e-8 * np.trace(G) / len(G) * np.eye(len(G)), Phi @ A.T).T
        r, nm = len(s), len(G) - len(s) - Us[0].shape[0]
        self.s, self.h = s, h
        self.Aq, self.Dv = W[:, :r] / s, W[:, nm:nm + r] / s
        self.Wn, self.Wu = W[:, r:nm], W[:, nm + r:] / 1e4
        self.Li = np.linalg.inv(np.eye(r) - h * h * self.Aq - h * self.Dv)   # linear part implicit

    def run(self, U: np.ndarray) -> np.ndarray:
        r, h, s = len(self.s), self.h, self.s[:, None]
        q, v = np.zeros(r), np.zeros(r)
        out = np.full((r, U.shape[1]), np.nan)
        with np.errstate(over='ignore', invalid='ignore'):        # a blow-up ends the run
            for j in range(U.shape[1]):
                out[:, j] = q
                nl = self.Wn @ _monomials_up_to_3(q[:, None] / s)[r:, 0]
                v = self.Li @ (v + h * (self.Aq @ q + nl + self.Wu @ U[:, j]))
                q = q + h * v
                if not np.all(np.isfinite(q)):
                    break
        return out


def _reduced_rows(model: EelModel, V: np.ndarray, q_ref: np.ndarray, X: np.ndarray,
                  eps: list, tests: list) -> tuple[float, dict[str, list[float]]]:
    """The four reduced models of check 7 at one r: test errors, and the cubic force's fit."""
    h, C = 1e-3, model.output_matrix('xz')
    red = _Reduced(model, V, q_ref, h)
    Q = V.T @ X
    s = Q.std(axis=1)[:, None]
    F = np.stack([red.elastic(Q[:, j]) for j in range(Q.shape[1])], axis=1)
    P = _monomials_up_to_3(Q / s)
    G = P @ P.T
    W = np.linalg.solve(G + 1e-10 * np.trace(G) / len(G) * np.eye(len(G)), P @ F.T).T
    fit = float(np.linalg.norm(F - W @ P) / np.linalg.norm(F))

    def cubic(q: np.ndarray) -> np.ndarray:
        return W @ _monomials_up_to_3(q[:, None] / s)[:, 0]

    forces = {'Galerkin': lambda q, u: red.elastic(q) + red.follower(q, u),
              'cubic force, follower loads': lambda q, u: cubic(q) + red.follower(q, u),
              'cubic force, dead loads': lambda q, u: cubic(q) + red.B @ u}
    y_ref = C @ q_ref

    def error(te: Any, Y: np.ndarray) -> float:               # inf: the model blew up
        return (relative_deviation_error(np.asarray(te.Y), Y, y_ref)
                if np.all(np.isfinite(Y)) else np.inf)

    rows = {label: [error(te, red.run(np.asarray(te.U), C, force)) for te in tests]
            for label, force in forces.items()}
    fitted = _EquationErrorCubic([V.T @ (np.asarray(ep.Q[:, :]) - q_ref[:, None]) for ep in eps],
                                 [np.asarray(ep.U) for ep in eps], h)
    rows['equation-error cubic fit'] = [
        error(te, C @ (q_ref[:, None] + V @ fitted.run(np.asarray(te.U)))) for te in tests]
    return fit, rows


def reduced_dynamics(eps: list, tests: list, V_all: np.ndarray, q_ref: np.ndarray,
                     rs: tuple[int, ...]) -> None:
    """Galerkin, exact-force cubic and equation-error cubic reduced models on the tests (7)."""
    model = EelModel()
    X = np.concatenate([np.asarray(ep.Q[:, ::10]) - q_ref[:, None] for ep in eps], axis=1)
    print('7. Reduced dynamics on the test episodes, deviation error (the cubic force: fitted '
          'to the exact reduced forces of the projected training states):')
    for r in rs:
        fit, rows = _reduced_rows(model, V_all[:, :r], q_ref, X, eps, tests)
        print(f'   r = {r:2d} (cubic fit of the reduced force: residual {fit:.1e})', flush=True)
        for label, e in rows.items():
            print(f'      {label:28s} ' + ' / '.join(f'{v:.3f}' for v in e), flush=True)


def _reprojected(model: EelModel, Wf: np.ndarray, q_ref: np.ndarray, eps: list,
                 stride: int = 10, h: float = 1e-3, scales: tuple[float, ...] = ()
                 ) -> tuple[np.ndarray, ...]:
    """``(z, ż, z̈, u)`` of the FOM's right-hand side at projected training states (9).

    With ``scales``, also at each projected state scaled by each factor (same ``ż`` and
    ``u``): states beyond the training data, where the FOM says what the force is.
    """
    free, cfg = model.free, model.config
    _, K0, m = model._rest_factor(h)
    out: list[list[np.ndarray]] = [[], [], [], []]
    for ep in eps:
        X, U = np.asarray(ep.Q[:, :]), np.asarray(ep.U)
        for j in range(stride, X.shape[1], stride):
            z1 = Wf.T @ (m * (X[:, j] - q_ref)[free])
            zd = Wf.T @ (m * ((X[:, j] - X[:, j - 1]) / h)[free])
            for z in [z1] + [a * z1 for a in scales]:
                x = q_ref.copy()
                x[free] += Wf @ z
                x3 = x.reshape(-1, 3)
                f = (model.fem.elastic_force(x3)
                     + model.pressure_force(x3, U[:, j])).ravel()[free]
                zdd = (Wf.T @ f - cfg.rayleigh_mass * zd
                       - cfg.rayleigh_stiffness * (Wf.T @ (K0 @ (Wf @ zd))))
                for lst, v in zip(out, (z, zd, zdd, U[:, j])):
                    lst.append(v)
    return tuple(np.array(lst).T for lst in out)


def _run_second_order(ops: tuple, U: np.ndarray, h: float = 1e-3) -> np.ndarray:
    """``z̈ + C ż + K z + ½ G(z,z) + ⅙ H(z,z,z) = B u`` from rest (K, C implicit), ``Z``."""
    from soft_rom.learners.lopinf.cubic import _nl_force
    K, C, B, G, H = ops
    r = K.shape[0]
    A = np.linalg.inv(np.eye(r) + h * C + h * h * K)
    z, v, Z = np.zeros(r), np.zeros(r), np.full((r, U.shape[1]), np.nan)
    for j in range(U.shape[1]):
        Z[:, j] = z
        f = K @ z + (0.0 if G is None else _nl_force(z[:, None], G, H)[:, 0])
        v = A @ (v + h * (B @ U[:, j] - f))
        z = z + h * v
        if not np.all(np.isfinite(z)) or np.abs(z).max() > 1e6:
            break
    return Z


def _long_run(model: Any, U: np.ndarray) -> tuple[np.ndarray, float]:
    """Outputs of ``model`` stepped on ``U`` from rest, and when it blew up.

    The time (s) of a blow-up is ``inf`` when the run stays finite; the implicit step
    failing counts as a blow-up (the outputs are NaN from there).
    """
    from soft_rom.errors import SoftRomError
    step, x = model.stepper(model.dt), np.zeros(model.n_states)
    Y = np.full((model.n_outputs, U.shape[1]), np.nan)
    for j in range(U.shape[1]):
        Y[:, j] = model.y_ref + model.E @ x[:model.r]     # the output at sample j, as simulate
        try:
            x = step(x, U[:, j])
        except (SoftRomError, np.linalg.LinAlgError):
            return Y, (j + 1) * model.dt
        if not np.all(np.isfinite(x)):
            return Y, (j + 1) * model.dt
    return Y, math.inf


def _cubic_report(rom: Any, tests: list, base: list[float], U_long: np.ndarray,
                  dev_train: float) -> str:
    """Check 9's test errors, their ratio to ``base``, and the 10 × longer inputs' run."""
    e = []
    for te in tests:
        Y, t_up = _long_run(rom, np.asarray(te.U))
        e.append(math.inf if math.isfinite(t_up)
                 else relative_deviation_error(np.asarray(te.Y), Y, rom.y_ref))
    Y, t_up = _long_run(rom, U_long)
    peak = float(np.abs(Y - rom.y_ref[:, None]).max()) / dev_train
    return ('test ' + ' / '.join(f'{v:.3f}' for v in e) + '; × linear (trajectories) '
            + ' / '.join(f'{a / b:.2f}' for a, b in zip(e, base))
            + f'; 10 × longer inputs ({U_long.shape[1]} samples): '
            + (f"bounded, peak deviation {peak:.2f} × the training data's"
               if math.isinf(t_up) else f'blows up at {t_up:.2f} s'))


def _trajectory_data(eps: list, V: np.ndarray, train: Any) -> Any:
    """The episodes' projected trajectories ``Vᵀ (x - q_ref)`` as the learners take them."""
    from soft_rom.reduce.data import ReducedData
    q_ref, y_ref = np.asarray(train.q_ref), np.asarray(train.y_ref)
    X = [V.T @ (np.asarray(ep.Q[:, :]) - q_ref[:, None]) for ep in eps]
    return ReducedData(coordinates=tuple(X), U=tuple(np.asarray(ep.U) for ep in eps),
                       Y=tuple(np.asarray(ep.Y) for ep in eps),
                       t=tuple(np.asarray(ep.t) for ep in eps), y_ref=y_ref,
                       names=tuple(ep.name for ep in eps), basis='pod',
                       n_states=len(q_ref), q_ref=q_ref, modes=V,
                       channels={k: getattr(train, k) for k in (
                           'input_names', 'output_names', 'input_units', 'output_units')})


def _mass_orthonormal(model: EelModel, V_all: np.ndarray, r: int) -> np.ndarray:
    """``W`` on the free DOFs spanning the first r POD modes, ``Wᵀ M W = I``."""
    Vf, m = V_all[model.free, :r], model._rest_factor(1e-3)[2]
    return np.linalg.solve(np.linalg.cholesky(Vf.T @ (m[:, None] * Vf)), Vf.T).T


def _long_inputs(tests: list, eps: list, y_ref: np.ndarray) -> tuple[np.ndarray, float]:
    """10 × longer inputs than a training episode, and the training outputs' largest deviation.

    The test inputs chained, as the learning curve's bounded check builds them.
    """
    U_long = np.concatenate([np.asarray(tests[i % len(tests)].U) for i in range(10)], axis=1)
    return U_long, max(float(np.abs(np.asarray(ep.Y) - y_ref[:, None]).max()) for ep in eps)


def reprojection(eps: list, tests: list, V_all: np.ndarray, train: Any,
                 rs: tuple[int, ...], scales: tuple[float, ...] = (), sos: bool = False
                 ) -> None:
    """Cubic and linear LOpInf operators fitted to re-projected data (9)."""
    from soft_rom.learners.lopinf import LOpInf
    import soft_rom.learners.lopinf.cubic as cub
    from soft_rom.learners.lopinf.solvers import DEFAULT_EPS, FastSPDSolver
    from soft_rom.models.cubic import CubicSecondOrderModel
    from soft_rom.models.tensors import quartic_lower_bound
    model = EelModel()
    q_ref, y_ref = np.asarray(train.q_ref), np.asarray(train.y_ref)
    C_out, free = model.output_matrix('xz'), model.free
    data = _trajectory_data(eps, V_all, train)
    # 10 x longer inputs than a training episode: the test inputs chained (as the learning
    # curve's bounded check builds them), and the training outputs' largest deviation
    U_long, dev_train = _long_inputs(tests, eps, y_ref)
    print('9. Re-projected training data' + (f' (and the states scaled by {scales})'
                                              if scales else '')
          + ': deviation error on the test episodes')
    for r in rs:
        t0 = time.perf_counter()
        Wf = _mass_orthonormal(model, V_all, r)
        Z, Zd, Zdd, U = _reprojected(model, Wf, q_ref, eps, scales=scales)
        s = float(np.sqrt(np.mean(Z ** 2)))
        lay = cub._Layout(r, U.shape[0])
        lin = FastSPDSolver().solve(Z / s, Zd / s, Zdd / s, U, eps=DEFAULT_EPS)
        E = C_out[:, free] @ Wf * s
        traj = LOpInf(r=r).fit(data)

        def errors(ops: tuple, E: np.ndarray = E) -> list[float]:
            return [relative_deviation_error(np.asarray(te.Y), y_ref[:, None]
                                             + E @ _run_second_order(ops, np.asarray(te.U)),
                                             y_ref) for te in tests]

        base = [relative_deviation_error(np.asarray(te.Y), traj.predict(np.asarray(te.U)),
                                         y_ref) for te in tests]
        print(f'   r = {r:2d}, {Z.shape[1]} states; linear LOpInf of the trajectories '
              + ' / '.join(f'{v:.3f}' for v in base) + ', of the re-projected data '
              + ' / '.join(f'{v:.3f}' for v in errors((lin.K, lin.C, lin.B, None, None))),
              flush=True)
        for reg in (0.0, 1e-8):
            t1 = time.perf_counter()
            K, Cd, G, H, B = lay.unpack(cub._least_squares(lay, Z / s, Zd / s, Zdd / s, U,
                                                           reg)[0].theta)
            t_ls = time.perf_counter() - t1
            res = Zdd / s + Cd @ (Zd / s) + K @ (Z / s) + cub._nl_force(Z / s, G, H) - B @ U
            # the library's model: the energy-consistent implicit step
            rom = CubicSecondOrderModel(K, Cd, G, H, B, E, dt=1e-3, y_ref=y_ref)
            Qr = np.random.default_rng(0).standard_normal((r, 20000))
            q4 = np.einsum('ijkl,it,jt,kt,lt->t', H, Qr, Qr, Qr, Qr)
            print(f'      cubic, reg {reg:g}: least squares {t_ls:.0f} s, relative residual '
                  f'{np.linalg.norm(res) / np.linalg.norm(Zdd / s):.1e}, smallest eigenvalue '
                  f'K {np.linalg.eigvalsh(K)[0]:.3g}, C {np.linalg.eigvalsh(Cd)[0]:.3g}, '
                  f'quartic bound (canonical Gram) {quartic_lower_bound(H, sdp=False)[0]:.3g}, '
                  f'quartic < 0 in {np.mean(q4 < 0):.0%} of random directions; '
                  + _cubic_report(rom, tests, base, U_long, dev_train), flush=True)
            if reg == 0.0 and sos:
                _sos_line((Z / s, Zd / s, Zdd / s, U), E, y_ref, tests, base, U_long,
                          dev_train)
        print(f'      ({time.perf_counter() - t0:.0f} s)', flush=True)


def _sos_line(data: tuple, E: np.ndarray, y_ref: np.ndarray, tests: list, base: list[float],
              U_long: np.ndarray, dev_train: float) -> None:
    """Check 9's certified variant: the library's ``quartic='projected'``, ``reg`` 0."""
    from soft_rom.errors import SolverError
    from soft_rom.learners.lopinf.cubic import fit_cubic
    from soft_rom.models.cubic import CubicSecondOrderModel
    try:
        sol = fit_cubic(*data, reg=0.0, quartic='projected')
    except SolverError as err:
        print(f'      quartic projected onto sums of squares: not fitted ({err})')
        return
    info = sol.info
    rom = CubicSecondOrderModel(sol.K, sol.C, sol.G, sol.H, sol.B, E, dt=1e-3, y_ref=y_ref)
    how = (f"SCS {info['projection_status']}, {info['projection_seconds']:.0f} s; Gram matrix "
           f"shifted by {info['projection_shift']:.3g}" if 'projection_seconds' in info
           else "the least squares' quartic already certified")
    print(f"      cubic, reg 0, quartic='projected' ({info['time_s']:.0f} s in all; {how}; "
          f"certified H(q⁴) ≥ {info['quartic_lower_bound']:.3g} |q / e|⁴, target "
          f"{info['quartic_target']:.3g}): "
          + _cubic_report(rom, tests, base, U_long, dev_train), flush=True)


def reprojected_selection(eps: list, tests: list, V_all: np.ndarray, train: Any,
                          rs: tuple[int, ...], folds: int = 4) -> None:
    """The certified re-projected cubic LOpInf's r, chosen on held-out training episodes (10).

    The training episodes are split into ``folds`` interleaved groups (as the library's
    selection does); every candidate r is fitted (``quartic='projected'``, ``reg`` 0) on the
    other groups' re-projected data and run on the held-out episodes' inputs; the score is
    the pooled relative deviation error over everything held out (``inf`` when a fit is
    refused or a run blows up). The linear LOpInf of the trajectories at the same r is
    scored on the same folds. The test episodes are used once, after the choice.
    """
    from soft_rom.errors import SolverError
    from soft_rom.learners.lopinf import LOpInf
    from soft_rom.learners.lopinf.cubic import fit_cubic
    from soft_rom.models.cubic import CubicSecondOrderModel
    from soft_rom.pipeline.cubic import folds_of
    model = EelModel()
    q_ref, y_ref = np.asarray(train.q_ref), np.asarray(train.y_ref)
    C_out, free = model.output_matrix('xz'), model.free
    groups = folds_of(len(eps), folds)
    U_long, dev_train = _long_inputs(tests, eps, y_ref)

    def pooled(Ys: list[np.ndarray], Yh: list[np.ndarray]) -> float:
        return relative_deviation_error(np.hstack(Ys), np.hstack(Yh), y_ref)

    def cubic(parts: list[tuple], Wf: np.ndarray) -> tuple[Any, float]:
        Z, Zd, Zdd, U = (np.concatenate([p[i] for p in parts], axis=1) for i in range(4))
        s = float(np.sqrt(np.mean(Z ** 2)))
        t0 = time.perf_counter()
        sol = fit_cubic(Z / s, Zd / s, Zdd / s, U, reg=0.0, quartic='projected')
        E = C_out[:, free] @ Wf * s
        return (CubicSecondOrderModel(sol.K, sol.C, sol.G, sol.H, sol.B, E, dt=1e-3,
                                      y_ref=y_ref), time.perf_counter() - t0)

    def linear(idx: list[int], r: int) -> Any:
        return LOpInf(r=r).fit(_trajectory_data([eps[i] for i in idx], V_all[:, :r], train))

    def run(rom: Any, U: np.ndarray) -> np.ndarray:
        Y, t_up = _long_run(rom, U)
        return Y if math.isinf(t_up) else np.full_like(Y, np.inf)

    print(f'10. r of the certified re-projected cubic LOpInf chosen on {len(groups)} folds of '
          f'the {len(eps)} training episodes (reg 0, quartic projected); pooled held-out '
          'deviation error, the linear LOpInf of the trajectories at the same r beside it:')
    scores: dict[int, tuple[float, float]] = {}
    for r in rs:
        t0 = time.perf_counter()
        Wf = _mass_orthonormal(model, V_all, r)
        parts = [_reprojected(model, Wf, q_ref, [ep]) for ep in eps]
        held: dict[str, tuple[list, list]] = {'cubic': ([], []), 'linear': ([], [])}
        fit_s = []
        for g in groups:
            rest = [i for i in range(len(eps)) if i not in g]
            try:
                rom, sec = cubic([parts[i] for i in rest], Wf)
                fit_s.append(sec)
                Yc = [run(rom, np.asarray(eps[i].U)) for i in g]
            except SolverError as err:
                print(f'      r = {r}, fold {g}: cubic not fitted ({err})', flush=True)
                Yc = [np.full_like(np.asarray(eps[i].Y), np.inf) for i in g]
            lin = linear(rest, r)
            held['cubic'][1].extend(Yc)
            held['linear'][1].extend(lin.predict(np.asarray(eps[i].U)) for i in g)
            for key in held:
                held[key][0].extend(np.asarray(eps[i].Y) for i in g)
        sc = (pooled(*held['cubic']), pooled(*held['linear']))
        scores[r] = sc
        print(f'   r = {r:2d}: held-out cubic {sc[0]:.3f}, linear {sc[1]:.3f} '
              f'({sc[0] / sc[1]:.2f} x); cubic fits {min(fit_s, default=math.nan):.0f}-'
              f'{max(fit_s, default=math.nan):.0f} s; '
              f'({time.perf_counter() - t0:.0f} s)', flush=True)
    best = min(scores, key=lambda r: scores[r][0])
    print(f'   chosen: r = {best} (held-out {scores[best][0]:.3f}); fitted on all '
          f'{len(eps)} training episodes, then the test episodes:', flush=True)
    Wf = _mass_orthonormal(model, V_all, best)
    rom, sec = cubic([_reprojected(model, Wf, q_ref, [ep]) for ep in eps], Wf)
    traj = linear(list(range(len(eps))), best)
    base = [relative_deviation_error(np.asarray(te.Y), traj.predict(np.asarray(te.U)), y_ref)
            for te in tests]
    print('      linear LOpInf of the trajectories ' + ' / '.join(f'{v:.3f}' for v in base)
          + f'; cubic ({sec:.0f} s) ' + _cubic_report(rom, tests, base, U_long, dev_train),
          flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--data', type=Path, default=Path('/tmp/cubic_cache/eel_reduced.npz'))
    ap.add_argument('--r', type=int, default=6)
    ap.add_argument('--cutoff', type=float, default=5.0, help='low-pass cut-off (Hz)')
    ap.add_argument('--gen-r', type=int, nargs='+', default=[4, 8, 22],
                    help='r of the equation-generalization check (5.)')
    ap.add_argument('--only-gen', action='store_true', help='run the check 5. only')
    ap.add_argument('--projection', type=Path, nargs=2, metavar=('TRAIN', 'TEST'),
                    help='run the check 6. only, on these two training sets')
    ap.add_argument('--projection-n', type=int, default=16,
                    help='training episodes of the POD (6.)')
    ap.add_argument('--projection-r', type=int, nargs='+', default=[4, 6, 8, 12, 16],
                    help='r of the check 6.')
    ap.add_argument('--dynamics', action='store_true',
                    help='with --projection: also the reduced dynamics (7.)')
    ap.add_argument('--closure', action='store_true',
                    help='with --projection: also the closure error (8.)')
    ap.add_argument('--reproject', action='store_true',
                    help='with --projection: also fits to re-projected data (9.)')
    ap.add_argument('--reproject-scale', type=float, nargs='*', default=[],
                    help='with --reproject: also re-project the states scaled by these')
    ap.add_argument('--reproject-sos', action='store_true',
                    help='with --reproject: also the quartic moved to a sum of squares')
    ap.add_argument('--reproject-select', action='store_true',
                    help='with --projection: r of the certified re-projected cubic LOpInf '
                    'chosen on held-out training episodes among --projection-r (10.)')
    args = ap.parse_args()
    if args.projection:
        t0 = time.perf_counter()
        representation(*args.projection, args.projection_n, tuple(args.projection_r),
                       dynamics=args.dynamics, closure=args.closure,
                       reproject=args.reproject, scales=tuple(args.reproject_scale),
                       sos=args.reproject_sos, select=args.reproject_select)
        print(f'({time.perf_counter() - t0:.0f} s)')
        return
    if not args.data.exists():
        args.data.parent.mkdir(parents=True, exist_ok=True)
        bce.build_data(args.data)
    data = bce.Data(args.data, args.r)
    t0 = time.perf_counter()
    if not args.only_gen:
        amplitude_scan(data.U[3], (1.0, 0.3, 0.1, 0.01))
        residual_families(data, args.cutoff)
        mirror_check()
    equation_generalization(args.data, tuple(args.gen_r), args.cutoff)
    print(f'({time.perf_counter() - t0:.0f} s)')


if __name__ == '__main__':
    main()
