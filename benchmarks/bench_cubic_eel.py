"""Benchmark: cubic vs linear LOpInf on the eel's study 2 (train Ep 1 + Ep 2, test Ep 3 - 6).

The acceptance point measured: the cubic (quartic-potential) LOpInf's relative deviation
error ``|Y - Ŷ| / |Y - y_ref|`` (Frobenius, per test episode) at most 0.5 x linear LOpInf's
at the same ``r`` on at least 3 of the 4 test episodes, and no blow-up on any test episode or
on inputs 10 x longer than a training episode (test inputs chained, as ``soft-rom study``
does).

Data: the study's default eel (six 2-s episodes at 1 ms, 50 kPa antagonistic random
pressures, mesh resolution 1), reduced as the study reduces it: POD of Ep 1 + Ep 2 about the
first snapshot, 22 modes, every episode projected. The FEM simulation takes minutes on two
cores, so the reduced arrays are cached in ``--data`` (default
``/tmp/cubic_cache/eel_reduced.npz``; arrays ``Q1``…``Q6``, ``U*``, ``Y*``, ``y_ref``,
``dt``; made here with the study's own pipeline when missing, never inside the repository).

Rows of the table, for each ``r``:

* ``linear``: ``LOpInf(r)`` as the study fits it (the baseline);
* ``floor``: the error of ``E q`` with the *true* reduced coordinates of the test episode
  (``E`` from the training fit): no ROM of that ``r`` with an output map ``y = E q + y_ref``
  does better, whatever its dynamics;
* ``library``: ``LOpInf(r, forces='cubic', cubic_options=CUBIC_EEL_OPTIONS)`` (the study's
  cubic model, equation error, conic constraints);
* ``correction``: ``K, C, B`` of the linear fit kept, ``G, H`` fitted to its acceleration
  residual (ridge ``λ``), ``λ`` chosen by the simulated deviation error across the two
  training episodes (fit on one, simulate the other) among the candidates that stay finite;
* ``oe``: ``G, H`` fitted on the *simulation* error of the training episodes' outputs
  (Levenberg-Marquardt on an RK4 simulation with forward sensitivities, from the linear
  model), ``K, C, B`` kept; ``--parity`` restricts ``G, H`` to the entries allowed by the
  eel's mirror symmetry (a mode is odd when ``E`` maps it mostly to the lateral ``z``
  outputs; ``V(q)`` even in the odd modes) -- an approximation: the discrete eel's mesh is
  not mirror-symmetric (``bench_eel_nonlinearity.py``, section 4);
* ``oe-joint``: every operator (``K, C, B, G, H``) on the simulation error, with ridge
  ``--joint-lambda`` on ``G, H`` and on the change of ``K, C, B`` from the linear fit;
* ``oe-structured``: ``oe-joint`` with the library's structure at every iterate:
  ``K = L Lᵀ + eps I``, ``C`` likewise, and ``H(q⁴) = wᵀ(P Pᵀ + t I)w`` (a sum of squares
  above the floor ``t = 1e-6 λ_max(K)``), Gauss-Newton in the factors;
* ``ms-oe``, ``ms-structured``: ``oe-joint`` and ``oe-structured`` by multiple shooting:
  the training episodes cut into windows of ``--window`` steps, each simulated from the
  true (projected) state, so the criterion is the prediction error over the window
  (between the equation error, one step, and the whole-episode simulation error);
* ``--modes M`` (with ``oe``, ``oe-joint``, ``capacity``, ``capacity-joint``): ``G, H``
  restricted to the monomials of ``M`` coordinates only (the first ``M``, or with
  ``--modes-by amplitude`` the ``M`` of largest RMS output contribution ``|E_i| q_i`` on the
  training episodes), ``--mode-parts G`` / ``H`` keeping only one of the two; ``oe-joint``
  then moves ``K, C, B`` too (ridge ``--joint-lambda``). ``M = 2``: 4 cubic + 5 quartic
  coefficients;
* ``oe-lowrank``: ``G = Σ a_j c_j⊗³``, ``H = Σ b_j c_j⊗⁴`` over ``--rank`` learned directions
  ``c_j`` (``K, C, B`` kept; ridge ``--oe-lambda``);
* ``oe-lin``: the same output-error fit of the *linear* operators ``K, C, B`` (``G = H = 0``),
  to separate what the fitting criterion gives from what the nonlinearity gives;
* ``capacity``, ``capacity-joint``, ``capacity-structured``, ``capacity-lin``
  (``--capacity``): ``oe``, ``oe-joint`` and ``oe-structured`` (ridge ``--oe-lambda`` on
  ``G, H`` only) and ``oe-lin`` fitted on all six episodes, test
  episodes included. Not valid models (they have seen the test data): they show what each
  model class can do when the data pin it down.

Run::

    .venv/bin/python benchmarks/bench_cubic_eel.py [--r 4 6] [--capacity] [--parity]
        [--variants library correction oe oe-joint oe-lin ms-oe ms-structured]
        [--window 250] [--modes M [--modes-by amplitude] [--mode-parts G|H]]
        [--variants oe-lowrank --rank 1]

Output of one run (two busy cores, 2026-12-02) is quoted in docs/methods_variants.md.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
import tempfile
import time
from typing import Any
import warnings

import numpy as np
import scipy.sparse as sp

from soft_rom.ddt import FiniteDifference
from soft_rom.learners.lopinf import cubic as lc
from soft_rom.learners.lopinf import LOpInf
from soft_rom.metrics import relative_deviation_error
from soft_rom.models.cubic import CubicSecondOrderModel
from soft_rom.models.tensors import symmetric_entries
from soft_rom.reduce import ReducedData

TRAIN, TESTS = (1, 2), (3, 4, 5, 6)
VARIANTS = ('library', 'correction', 'oe', 'oe-lin', 'oe-joint', 'oe-structured', 'ms-oe',
            'ms-structured', 'oe-lowrank', 'capacity',
            'capacity-joint', 'capacity-lin', 'capacity-structured')


# ------------------------------------------------------------------------------ data
def build_data(path: Path) -> None:
    """Simulate the study's default eel, convert, reduce as study 2 does; save ``path``."""
    from soft_rom.basis import POD, project
    from soft_rom.convert import convert
    from soft_rom.study.fits import _in_memory
    from soft_rom.study.run import simulate_bags, StudyConfig
    cfg = StudyConfig()
    work = Path(tempfile.mkdtemp(prefix='cubic_eel_', dir=path.parent))
    t0 = time.perf_counter()
    bags = simulate_bags(work / 'bags', cfg, progress=True)
    ts, _ = convert(bags, work / 'data.zarr', overwrite=True, progress=True)
    eps = [_in_memory(ts[f'ep{i}']) for i in range(1, 7)]
    q_ref = np.asarray(ts.q_ref, dtype=np.float64)
    V = POD(r=22).fit([eps[0].Q, eps[1].Q], q_ref).basis_
    out: dict[str, Any] = {'y_ref': ts.y_ref, 'dt': eps[0].dt}
    for i, ep in enumerate(eps, 1):
        out[f'Q{i}'], out[f'U{i}'], out[f'Y{i}'] = project(ep.Q, V, q_ref), ep.U, ep.Y
    np.savez(path, **out)
    print(f'simulated and reduced the eel in {time.perf_counter() - t0:.0f} s -> {path} '
          f'(bags and zarr left in {work})')


class Data:
    """The cached reduced eel episodes, cut to ``r`` coordinates."""

    def __init__(self, path: Path, r: int) -> None:
        d = np.load(path)                      # plain arrays only (no pickle)
        self.r, self.dt, self.y_ref = r, float(d['dt']), np.asarray(d['y_ref'])
        self.Q = {i: np.asarray(d[f'Q{i}'][:r]) for i in range(1, 7)}
        self.U = {i: np.asarray(d[f'U{i}']) for i in range(1, 7)}
        self.Y = {i: np.asarray(d[f'Y{i}']) for i in range(1, 7)}

    def linear(self, eps: tuple[int, ...] = TRAIN) -> LOpInf:
        return LOpInf(r=self.r).fit(ReducedData.from_arrays(
            [self.Q[i] for i in eps], [self.U[i] for i in eps], [self.Y[i] for i in eps],
            self.dt, self.y_ref))

    def dev_errors(self, model: Any) -> dict[int, float]:
        out = {}
        for i in range(1, 7):
            try:
                with np.errstate(all='ignore'):
                    Yh = np.asarray(model.simulate(self.U[i]))
                ok = np.all(np.isfinite(Yh))
            except Exception:                  # a failed simulation is a result
                ok = False
            out[i] = relative_deviation_error(self.Y[i], Yh, self.y_ref) if ok else np.inf
        return out

    def long_inputs(self, model: Any, factor: int = 10) -> str:
        k = self.U[1].shape[1] * factor
        U = np.concatenate([self.U[TESTS[j % 4]] for j in range(factor)], axis=1)[:, :k]
        dev_train = max(float(np.max(np.abs(self.Y[i] - self.y_ref[:, None]))) for i in TRAIN)
        try:
            with np.errstate(all='ignore'):
                Y = np.asarray(model.simulate(U))
        except Exception as err:
            return f'failed ({type(err).__name__})'
        if not np.all(np.isfinite(Y)):
            return 'NOT finite (blow-up)'
        peak = float(np.max(np.abs(Y - self.y_ref[:, None]))) / dev_train
        return f'{"bounded" if peak <= 10 else "BLOW-UP"} ({peak:.3g} x training max)'


def scaled(data: Data, lin: LOpInf, eps: tuple[int, ...]) -> tuple[np.ndarray, ...]:
    """``Q, Q̇, Q̈, U`` of ``eps`` in the linear fit's scaled units (8th-order differences)."""
    s, su = lin.state_scale_, lin.input_scale_
    Q, Qd, Qdd, (U,) = FiniteDifference(order=8).episodes(
        [data.Q[i] / s for i in eps], data.dt, [[data.U[i] / su[:, None] for i in eps]])
    return Q, Qd, Qdd, U


def cubic_model(lin: LOpInf, G: np.ndarray, H: np.ndarray, K: np.ndarray | None = None,
                C: np.ndarray | None = None, Bs: np.ndarray | None = None
                ) -> CubicSecondOrderModel:
    """A cubic model from scaled-unit tensors on top of (or replacing) the linear operators."""
    m, s, su = lin.model_, lin.state_scale_, lin.input_scale_
    B = m.B if Bs is None else Bs * s / su[None, :]
    return CubicSecondOrderModel(m.K if K is None else K, m.C if C is None else C, G / s,
                                 H / s ** 2, B, m.E, dt=m.dt, y_ref=m.y_ref)


def parity_mask(lin: LOpInf, names_z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Entries of ``G`` and ``H`` allowed by mirror symmetry (even number of odd modes)."""
    E = lin.model_.E
    odd = np.linalg.norm(E[names_z], axis=0) > np.linalg.norm(E[~names_z], axis=0)
    r = E.shape[1]
    keep = [np.array([sum(odd[list(a)]) % 2 == 0 for a in lc.symmetric_index(r, d)])
            for d in (3, 4)]
    return keep[0], keep[1]


def mode_mask(r: int, modes: tuple[int, ...], parts: str = 'GH'
              ) -> tuple[np.ndarray, np.ndarray]:
    """Entries of ``G`` and ``H`` on the monomials of the coordinates ``modes`` only.

    ``V`` is then nonlinear in those (0-based) coordinates alone; ``parts`` ``'G'`` or ``'H'``
    keeps one of the two tensors.
    """
    ms = set(modes)
    keep = [np.array([set(a) <= ms and name in parts for a in lc.symmetric_index(r, d)],
                     dtype=bool) for name, d in (('G', 3), ('H', 4))]
    return keep[0], keep[1]


def amplitude_modes(data: Data, m: int, lin: LOpInf | None = None) -> tuple[int, ...]:
    """The ``m`` coordinates of largest RMS amplitude on the training episodes.

    The amplitude of ``q_i``, or of its output contribution ``E[:, i] q_i`` when ``lin`` is
    given.
    """
    Q = np.hstack([data.Q[i] for i in TRAIN])
    amp = np.sqrt(np.mean(Q ** 2, axis=1))
    if lin is not None:
        amp = amp * np.linalg.norm(lin.model_.E, axis=0)
    return tuple(sorted(int(i) for i in np.argsort(-amp)[:m]))


# ------------------------------------------------------------------------------ variants
def correction(data: Data, lin: LOpInf, lams: tuple[float, ...] = (1e-4, 1e-3, 1e-2, 1e-1, 1.0,
                                                                    10.0)
               ) -> tuple[CubicSecondOrderModel, str]:
    """``G, H`` on the linear model's acceleration residual; ridge chosen across episodes."""
    r, m = data.r, lin.model_.n_inputs
    lay = lc._Layout(r, m)
    o = lay.t_off
    cols = np.arange(o['G'], o['C'])
    w = np.concatenate([lay.tensor_weights('G'), lay.tensor_weights('H')])
    nG = len(lay.idx[3])
    Ks, Cs = lin.model_.K, lin.model_.C
    Bs = lin.model_.B * lin.input_scale_[None, :] / lin.state_scale_

    def normal(eps: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, int]:
        Q, Qd, Qdd, U = scaled(data, lin, eps)
        R = Qdd + Cs @ Qd + Ks @ Q - Bs @ U
        Z = lay.features(Q, Qd, U)
        A = np.vstack([(lay.L[i][:, cols].T @ Z).T for i in range(r)])
        return A.T @ A, -(A.T @ R.ravel()), Q.shape[1]

    def tensors(N: np.ndarray, g: np.ndarray, k: int, lam: float
                ) -> tuple[np.ndarray, np.ndarray]:
        th = np.linalg.solve(N + lam * k * np.diag(w), g)
        return (lc.symmetric_from_entries(th[:nG], r, 3),
                lc.symmetric_from_entries(th[nG:], r, 4))

    parts = {e: normal((e,)) for e in TRAIN}
    scores = []
    for lam in lams:
        err = 0.0
        for fit_on, test_on in ((1, 2), (2, 1)):
            G, H = tensors(*parts[fit_on], lam)
            e = data.dev_errors(cubic_model(lin, G, H))[test_on]
            err = max(err, e)
        scores.append(err)
    best = lams[int(np.argmin(scores))]
    N = parts[1][0] + parts[2][0]
    g = parts[1][1] + parts[2][1]
    G, H = tensors(N, g, parts[1][2] + parts[2][2], best)
    table = ', '.join(f'{lam:g}: {s:.3f}' for lam, s in zip(lams, scores))
    t4 = lc.quartic_lower_bound(H, target=0.0)[0]
    return cubic_model(lin, G, H), (f'λ = {best:g} (worst cross-episode error {table}); '
                                    f'quartic bound {t4:.3g}')


def levenberg_marquardt(x: np.ndarray,
                        linearize: Callable[[np.ndarray], tuple[float, Any, Any]],
                        cost: Callable[[np.ndarray], float],
                        step: Callable[[np.ndarray, np.ndarray], np.ndarray],
                        iters: int) -> tuple[np.ndarray, str]:
    """Levenberg-Marquardt with Marquardt scaling; a step is taken only if it lowers the cost.

    ``linearize(x) -> (J, A, b)``: cost, Gauss-Newton matrix and gradient at ``x``;
    ``cost(x)``: the cost alone; ``step(x, dx)``: ``x`` moved by the solution ``dx`` of
    ``(A + mu diag(A)) dx = -b``. Stops after ``iters`` steps, when no damping lowers the
    cost, or when a step gains less than 1e-6 of it.
    """
    J0, A, b = linearize(x)
    J, n = J0, len(b)
    mu = 1e-3 * float(np.trace(A)) / n
    steps = 0
    for _ in range(iters):
        Dg = np.diag(np.diag(A)) + 1e-12 * float(np.trace(A)) / n * np.eye(n)
        Jn = np.inf
        while mu < 1e12:
            trial = step(x, np.linalg.solve(A + mu * Dg, -b))
            Jn = cost(trial)
            if Jn < J:
                x, mu = trial, max(mu / 3.0, 1e-12)
                steps += 1
                break
            mu *= 4.0
        if mu >= 1e12 or J - Jn < 1e-6 * J:
            break
        J, A, b = linearize(x)
    return x, f'{steps} LM steps, cost {J0:.4g} -> {J:.4g}'


class OutputError:
    """Simulation-error fit of chosen entries of ``θ = (K, G, H, C, B)`` (scaled units).

    RK4 with the input held over each step, forward sensitivities, Levenberg-Marquardt on
    ``Σ_t |W (q_sim - q)|²`` with ``WᵀW = (s E)ᵀ(s E)`` (the output deviations), plus
    ``λ k (|G|² + |H|²)``. All episodes are simulated together (same length).
    """

    def __init__(self, data: Data, lin: LOpInf, which: str, lam: float,
                 eps: tuple[int, ...], keep: tuple[np.ndarray, np.ndarray] | None,
                 lam_lin: float = 0.0) -> None:
        r, m = data.r, lin.model_.n_inputs
        self.r, self.h, self.lam, self.lam_lin = r, data.dt, lam, lam_lin
        self.lay = lay = lc._Layout(r, m)
        o = lay.t_off
        self.P = lay.n_theta
        self.Lst = sp.vstack([lay.L[i].T for i in range(r)]).tocsr()
        th = np.zeros(self.P)
        mod = lin.model_
        th[o['K']:o['G']] = symmetric_entries(mod.K)
        th[o['C']:o['B']] = symmetric_entries(mod.C)
        th[o['B']:] = (mod.B * lin.input_scale_[None, :] / lin.state_scale_).ravel()
        self.theta = th
        self.w_lin = np.zeros(self.P)
        self.w_lin[o['K']:o['G']] = lay.tensor_weights('K')
        self.w_lin[o['C']:o['B']] = lay.tensor_weights('C')
        self.w_lin[o['B']:] = 1.0
        if which == 'all':
            free = np.arange(self.P)
        elif which == 'nl':
            free = np.arange(o['G'], o['C'])
            if keep is not None:
                free = free[np.concatenate(keep)]
        elif which == 'all-masked':             # K, C, B and the entries of G, H in keep
            assert keep is not None
            free = np.r_[np.arange(o['K'], o['G']), np.arange(o['G'], o['C'])[
                np.concatenate(keep)], np.arange(o['C'], self.P)]
        else:                                   # the linear operators
            free = np.r_[np.arange(o['K'], o['G']), np.arange(o['C'], self.P)]
        self.free = free
        rows = (np.arange(r)[:, None] * self.P + free[None, :]).ravel()
        self.Lfree = self.Lst[rows]             # the rows of Lst of the free unknowns only
        self.w = np.zeros(self.P)
        self.w[o['G']:o['C']] = np.concatenate([lay.tensor_weights('G'),
                                                lay.tensor_weights('H')])
        Ws = mod.E * lin.state_scale_
        self.Wc = np.linalg.cholesky(Ws.T @ Ws + 1e-12 * np.eye(r)).T
        s, su = lin.state_scale_, lin.input_scale_
        self.Qt = np.stack([data.Q[i] / s for i in eps])              # (nb, r, k)
        self.Ut = np.stack([data.U[i] / su[:, None] for i in eps])    # (nb, m, k)
        self.X0: np.ndarray | None = None                             # (2r, nb); None: rest

    def use_windows(self, data: Data, lin: LOpInf, eps: tuple[int, ...], length: int) -> None:
        """Multiple shooting: fit on windows of ``length`` steps, each from the true state.

        The windows tile every episode of ``eps``; each starts at the projected FEM state
        (velocity by 8th-order differences), so the simulation error measures the prediction
        over ``length`` steps instead of over the whole episode.
        """
        s, su = lin.state_scale_, lin.input_scale_
        Qs, V0, Us = [], [], []
        for i in eps:
            q = data.Q[i] / s
            _, Qd, _ = FiniteDifference(order=8).episodes([q], data.dt)[:3]
            qd = Qd if isinstance(Qd, np.ndarray) else Qd[0]
            u = data.U[i] / su[:, None]
            for a in range(0, q.shape[1] - length + 1, length):
                Qs.append(q[:, a:a + length])
                V0.append(qd[:, a])
                Us.append(u[:, a:a + length])
        self.Qt, self.Ut = np.stack(Qs), np.stack(Us)
        self.X0 = np.vstack([self.Qt[:, :, 0].T, np.stack(V0).T])

    def _simulate(self, th: np.ndarray, sens: bool) -> tuple[np.ndarray | None, Any]:
        r, h, lay = self.r, self.h, self.lay
        K, C, G, H, B = lay.unpack(th)
        nb, _, k = self.Qt.shape
        nf = len(self.free)
        x = np.zeros((2 * r, nb)) if self.X0 is None else self.X0.copy()
        S = np.zeros((nb, 2 * r, nf))
        Xq = np.empty((k, r, nb))
        Sq = np.empty((k, nb, r, nf)) if sens else None
        i2, i3 = lay.idx[2], lay.idx[3]
        a2 = np.array(i2).T
        a3 = np.array(i3).T

        def f(x: np.ndarray, u: np.ndarray) -> np.ndarray:
            q, v = x[:r], x[r:]
            a = -(K @ q + 0.5 * np.einsum('ijk,jb,kb->ib', G, q, q)
                  + np.einsum('ijkl,jb,kb,lb->ib', H, q, q, q) / 6.0 + C @ v - B @ u)
            return np.vstack([v, a])

        def df(x: np.ndarray, u: np.ndarray, S: np.ndarray) -> np.ndarray:
            q, v = x[:r], x[r:]
            Kt = (K[None] + np.einsum('ijk,kb->bij', G, q)
                  + 0.5 * np.einsum('ijkl,kb,lb->bij', H, q, q))
            Z = np.vstack([q, q[a2[0]] * q[a2[1]], q[a3[0]] * q[a3[1]] * q[a3[2]], v, u])
            Mz = (self.Lfree @ Z).reshape(r, nf, nb).transpose(2, 0, 1)
            return np.concatenate([S[:, r:], -Kt @ S[:, :r] - C @ S[:, r:] - Mz], axis=1)

        for j in range(k):
            Xq[j] = x[:r]
            if sens:
                Sq[j] = S[:, :r]
            if not np.all(np.abs(x) < 1e3):
                return None, None
            u = self.Ut[:, :, j].T
            k1 = f(x, u)
            x2 = x + 0.5 * h * k1
            k2 = f(x2, u)
            x3 = x + 0.5 * h * k2
            k3 = f(x3, u)
            x4 = x + h * k3
            k4 = f(x4, u)
            if sens:
                d1 = df(x, u, S)
                d2 = df(x2, u, S + 0.5 * h * d1)
                d3 = df(x3, u, S + 0.5 * h * d2)
                d4 = df(x4, u, S + h * d3)
                S = S + h / 6.0 * (d1 + 2 * d2 + 2 * d3 + d4)
            x = x + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        return Xq, Sq

    def cost(self, th: np.ndarray, sens: bool = True) -> tuple[float, Any, Any]:
        Xq, Sq = self._simulate(th, sens)
        if Xq is None:
            return np.inf, None, None
        e = np.einsum('ab,kbn->kna', self.Wc, Xq - self.Qt.transpose(2, 1, 0))   # (k, nb, r)
        n = self.Qt.shape[0] * self.Qt.shape[2]
        w = self.lam * n * self.w + self.lam_lin * n * self.w_lin    # ridge weights
        ref = np.where(self.w > 0, 0.0, self.theta)                   # G, H -> 0; K, C, B -> fit
        J = float(np.sum(e ** 2)) + float(w @ (th - ref) ** 2)
        if not sens:
            return J, None, None
        Jt = np.einsum('ab,knbp->knap', self.Wc, Sq).reshape(-1, len(self.free))
        f = self.free
        JTJ = Jt.T @ Jt + np.diag(w[f])
        g = Jt.T @ e.reshape(-1) + w[f] * (th - ref)[f]
        return J, JTJ, g

    def fit(self, iters: int) -> tuple[np.ndarray, str]:
        def step(th: np.ndarray, dx: np.ndarray) -> np.ndarray:
            out = th.copy()
            out[self.free] += dx
            return out

        return levenberg_marquardt(self.theta.copy(), self.cost,
                                   lambda th: self.cost(th, sens=False)[0], step, iters)


def oe(data: Data, lin: LOpInf, which: str, lam: float, iters: int,
       eps: tuple[int, ...] = TRAIN, keep: tuple[np.ndarray, np.ndarray] | None = None,
       lam_lin: float = 0.0, window: int = 0) -> tuple[CubicSecondOrderModel | Any, str]:
    fit = OutputError(data, lin, which, lam, eps, keep, lam_lin)
    if window:
        fit.use_windows(data, lin, eps, window)
    th, how = fit.fit(iters)
    if window:
        how += f'; {fit.Qt.shape[0]} windows of {window} steps'
    K, C, G, H, Bs = fit.lay.unpack(th)
    C = 0.5 * (C + C.T)
    lam_k, lam_c = np.linalg.eigvalsh(K)[0], np.linalg.eigvalsh(C)[0]
    t4 = lc.quartic_lower_bound(H, target=0.0)[0] if which != 'lin' else 0.0
    how += f'; min eig K {lam_k:.3g}, C {lam_c:.3g}; quartic bound {t4:.3g}'
    if which in ('all', 'all-masked'):
        how += f'; ridge {lam:g} on G, H and {lam_lin:g} on the change of K, C, B'
        return cubic_model(lin, G, H, K, C, Bs), how
    if which == 'nl':
        return cubic_model(lin, G, H), how
    from soft_rom.models import SecondOrderModel
    mod = lin.model_
    if lam_k <= 0 or lam_c <= 0:
        how += ' (K or C not SPD)'
    return SecondOrderModel(K, C, Bs * lin.state_scale_ / lin.input_scale_[None, :], mod.E,
                            dt=mod.dt, y_ref=mod.y_ref), how


class LowRankOutputError(OutputError):
    """:class:`OutputError` of ``G, H`` of rank ``k`` in learned directions ``c_j``.

    ``G = Σ a_j c_j⊗c_j⊗c_j``, ``H = Σ b_j c_j⊗c_j⊗c_j⊗c_j`` (``K, C, B`` of the linear
    fit kept), so the nonlinear potential depends on ``k`` directions only (``k (r + 2)``
    unknowns). ``parts`` ``'G'`` / ``'H'`` keeps one of the two. Starts from ``c_j = e_j``,
    ``a = b = 0``.
    """

    def __init__(self, data: Data, lin: LOpInf, lam: float, eps: tuple[int, ...],
                 rank: int = 1, parts: str = 'GH') -> None:
        r = data.r
        keep = (np.ones(len(lc.symmetric_index(r, 3)), bool),
                np.ones(len(lc.symmetric_index(r, 4)), bool))
        super().__init__(data, lin, 'nl', lam, eps, keep)
        self.rank, self.parts = rank, parts
        self.i3 = np.array(lc.symmetric_index(r, 3))
        self.i4 = np.array(lc.symmetric_index(r, 4))
        self.phi = np.concatenate([np.eye(r)[:rank].ravel(), np.zeros(2 * rank)])

    def theta_of(self, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, k, o = self.r, self.rank, self.lay.t_off
        Cm = phi[:k * r].reshape(k, r)
        a, b = phi[k * r:k * r + k], phi[k * r + k:]
        if 'G' not in self.parts:
            a = 0 * a
        if 'H' not in self.parts:
            b = 0 * b
        nG, nH = len(self.i3), len(self.i4)
        th = self.theta.copy()
        D = np.zeros((nG + nH, len(phi)))        # d(G, H entries) / d phi
        g = np.zeros(nG)
        h = np.zeros(nH)
        for j in range(k):
            c = Cm[j]
            P3 = c[self.i3].prod(axis=1)
            P4 = c[self.i4].prod(axis=1)
            g += a[j] * P3
            h += b[j] * P4
            for idx, amp, rows, deg in ((self.i3, a[j], slice(0, nG), 3),
                                        (self.i4, b[j], slice(nG, nG + nH), 4)):
                dP = np.zeros((len(idx), r))
                for pos in range(deg):
                    others = np.delete(idx, pos, axis=1)
                    np.add.at(dP, (np.arange(len(idx)), idx[:, pos]),
                              c[others].prod(axis=1))
                D[rows, j * r:(j + 1) * r] = amp * dP
            if 'G' in self.parts:
                D[:nG, k * r + j] = P3
            if 'H' in self.parts:
                D[nG:, k * r + k + j] = P4
        th[o['G']:o['H']] = g
        th[o['H']:o['C']] = h
        return th, D

    def fit(self, iters: int) -> tuple[np.ndarray, str]:
        def linearize(phi: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
            th, D = self.theta_of(phi)
            J, JTJ, g = self.cost(th)
            if JTJ is None:
                return J, None, None
            return J, D.T @ JTJ @ D, D.T @ g

        phi, how = levenberg_marquardt(
            self.phi.copy(), linearize,
            lambda phi: self.cost(self.theta_of(phi)[0], sens=False)[0],
            lambda phi, dx: phi + dx, iters)
        self.phi_fit = phi
        return self.theta_of(phi)[0], how


def oe_lowrank(data: Data, lin: LOpInf, lam: float, iters: int, rank: int = 1,
               parts: str = 'GH', eps: tuple[int, ...] = TRAIN
               ) -> tuple[CubicSecondOrderModel, str]:
    fit = LowRankOutputError(data, lin, lam, eps, rank, parts)
    th, how = fit.fit(iters)
    K, C, G, H, Bs = fit.lay.unpack(th)
    t4 = lc.quartic_lower_bound(H, target=0.0)[0]
    Cm = fit.phi_fit[:rank * data.r].reshape(rank, data.r)
    how += (f'; rank-{rank} {parts}, directions '
            + '; '.join(np.array2string(c / np.linalg.norm(c), precision=2) for c in Cm)
            + f'; quartic bound {t4:.3g}; ridge {lam:g}')
    return cubic_model(lin, G, H), how


def _dgram(L: np.ndarray) -> np.ndarray:
    """``d vec(L Lᵀ) / d vec(L)`` (row-major vec), shape (n², n²)."""
    n = L.shape[0]
    eye = np.eye(n)
    comm = np.zeros((n * n, n * n))
    for a in range(n):
        for b in range(n):
            comm[a * n + b, b * n + a] = 1.0
    return np.kron(eye, L) + np.kron(L, eye) @ comm


class StructuredOutputError(OutputError):
    """:class:`OutputError` of every operator with the library's structure built in.

    ``K = L_K L_Kᵀ + eps I``, ``C = L_C L_Cᵀ + eps I`` (lower-triangular factors) and
    ``H(q⁴) = wᵀ(P Pᵀ + t I)w`` over the scaled quadratic monomials ``w`` (``|w|² = |q|⁴``),
    ``t = eps4 · λ_max(K₀)``: ``K, C ⪰ eps`` and the quartic is a certified sum of squares
    at every iterate. Gauss-Newton in the factors: ``J_φ = J_θ dθ/dφ``.
    """

    def __init__(self, data: Data, lin: LOpInf, lam: float, eps: tuple[int, ...],
                 lam_lin: float, eps_spd: float = 1e-6, eps4: float = 1e-6) -> None:
        super().__init__(data, lin, 'all', lam, eps, None, lam_lin)
        r, o = self.r, self.lay.t_off
        K0, C0, G0, _H0, B0 = self.lay.unpack(self.theta)
        self.eps_spd = eps_spd
        self.t4 = eps4 * float(np.linalg.eigvalsh(K0)[-1])
        self.Tg, self.ns = lc._gram_map(r)
        self.Tg = self.Tg.toarray()
        self.tri_r = np.tril_indices(r)
        self.tri_s = np.tril_indices(self.ns)
        self.sym = [r * a + b for a, b in lc.symmetric_index(r, 2)]   # K entries in vec(K)
        lk = np.linalg.cholesky(K0 - eps_spd * np.eye(r))[self.tri_r]
        lcf = np.linalg.cholesky(0.5 * (C0 + C0.T) - eps_spd * np.eye(r))[self.tri_r]
        p0 = 0.1 * np.eye(self.ns)[self.tri_s]
        self.phi = np.concatenate([lk, lcf, B0.ravel(), symmetric_entries(G0), p0])
        self.n_tri = len(lk)
        self.o = o

    def _split(self, phi: np.ndarray) -> tuple[np.ndarray, ...]:
        r, nt = self.r, self.n_tri
        nB, nG = r * self.Ut.shape[1], len(self.lay.idx[3])
        Lk = np.zeros((r, r))
        Lk[self.tri_r] = phi[:nt]
        Lc = np.zeros((r, r))
        Lc[self.tri_r] = phi[nt:2 * nt]
        B = phi[2 * nt:2 * nt + nB]
        G = phi[2 * nt + nB:2 * nt + nB + nG]
        P = np.zeros((self.ns, self.ns))
        P[self.tri_s] = phi[2 * nt + nB + nG:]
        return Lk, Lc, B, G, P

    def theta_of(self, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``θ(φ)`` and ``dθ/dφ``."""
        r, o = self.r, self.o
        Lk, Lc, B, G, P = self._split(phi)
        eye_r = np.eye(r)
        th = np.zeros(self.P)
        th[o['K']:o['G']] = (Lk @ Lk.T + self.eps_spd * eye_r).ravel()[self.sym]
        th[o['C']:o['B']] = (Lc @ Lc.T + self.eps_spd * eye_r).ravel()[self.sym]
        th[o['B']:] = B
        th[o['G']:o['H']] = G
        X = P @ P.T + self.t4 * np.eye(self.ns)
        th[o['H']:o['C']] = self.Tg @ X.ravel()
        D = np.zeros((self.P, len(phi)))
        cols_r = self.tri_r[0] * r + self.tri_r[1]
        cols_s = self.tri_s[0] * self.ns + self.tri_s[1]
        nt, nB, nG = self.n_tri, len(B), len(G)
        D[o['K']:o['G'], :nt] = _dgram(Lk)[np.ix_(self.sym, cols_r)]
        D[o['C']:o['B'], nt:2 * nt] = _dgram(Lc)[np.ix_(self.sym, cols_r)]
        D[o['B']:, 2 * nt:2 * nt + nB] = np.eye(nB)
        D[o['G']:o['H'], 2 * nt + nB:2 * nt + nB + nG] = np.eye(nG)
        D[o['H']:o['C'], 2 * nt + nB + nG:] = self.Tg @ _dgram(P)[:, cols_s]
        return th, D

    def fit(self, iters: int) -> tuple[np.ndarray, str]:
        def linearize(phi: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
            th, D = self.theta_of(phi)
            J, JTJ, g = self.cost(th)
            return J, D.T @ JTJ @ D, D.T @ g

        phi, how = levenberg_marquardt(
            self.phi.copy(), linearize,
            lambda phi: self.cost(self.theta_of(phi)[0], sens=False)[0],
            lambda phi, dx: phi + dx, iters)
        return self.theta_of(phi)[0], how


def oe_structured(data: Data, lin: LOpInf, lam: float, iters: int,
                  eps: tuple[int, ...] = TRAIN, lam_lin: float = 0.0, window: int = 0
                  ) -> tuple[CubicSecondOrderModel, str]:
    fit = StructuredOutputError(data, lin, lam, eps, lam_lin)
    if window:
        fit.use_windows(data, lin, eps, window)
    th, how = fit.fit(iters)
    if window:
        how += f'; {fit.Qt.shape[0]} windows of {window} steps'
    K, C, G, H, Bs = fit.lay.unpack(th)
    t4 = lc.quartic_lower_bound(H, target=0.0)[0]
    how += (f'; min eig K {np.linalg.eigvalsh(K)[0]:.3g}, C {np.linalg.eigvalsh(C)[0]:.3g}; '
            f'quartic bound {t4:.3g} (floor {fit.t4:.3g}); ridge {lam:g} on G, H and '
            f'{lam_lin:g} on the change of K, C, B')
    return cubic_model(lin, G, H, K, C, Bs), how


# ------------------------------------------------------------------------------ main
def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--data', type=Path, default=Path('/tmp/cubic_cache/eel_reduced.npz'))
    ap.add_argument('--r', type=int, nargs='+', default=[4, 6])
    ap.add_argument('--variants', nargs='+',
                    default=['library', 'correction', 'oe', 'oe-joint', 'oe-structured',
                             'oe-lin'],
                    choices=VARIANTS)
    ap.add_argument('--oe-lambda', type=float, default=1e-8)
    ap.add_argument('--oe-iters', type=int, default=8, help='LM steps of the Ep 1 + 2 fits')
    ap.add_argument('--capacity-iters', type=int, default=20, help='LM steps, capacity rows')
    ap.add_argument('--joint-lambda', type=float, default=1e-5,
                    help='oe-joint: ridge on G, H and on the change of K, C, B')
    ap.add_argument('--parity', action='store_true', help='mirror-symmetric G, H in oe')
    ap.add_argument('--window', type=int, default=250,
                    help='ms-oe, ms-structured: steps per multiple-shooting window')
    ap.add_argument('--capacity', action='store_true', help='add the capacity row')
    ap.add_argument('--modes', type=int, default=0,
                    help='G, H on the monomials of this many coordinates only (0: all)')
    ap.add_argument('--modes-by', choices=('index', 'amplitude'), default='index',
                    help='--modes: the first coordinates, or those of largest output amplitude')
    ap.add_argument('--mode-parts', choices=('GH', 'G', 'H'), default='GH',
                    help='--modes: keep G and H, or only one of them')
    ap.add_argument('--rank', type=int, default=1, help='oe-lowrank: number of directions')
    args = ap.parse_args()
    if not args.data.exists():
        args.data.parent.mkdir(parents=True, exist_ok=True)
        build_data(args.data)
    variants = list(args.variants) + (['capacity', 'capacity-joint', 'capacity-structured',
                                       'capacity-lin'] if args.capacity else [])
    from soft_rom.dataset import TrainingSet  # noqa: F401  (the study's reader; import check)
    from soft_rom.study.presets import CUBIC_EEL_OPTIONS
    for r in args.r:
        data = Data(args.data, r)
        lin = data.linear()
        e_lin = data.dev_errors(lin.model_)
        E = lin.model_.E
        floor = {i: relative_deviation_error(data.Y[i], E @ data.Q[i] + data.y_ref[:, None],
                                             data.y_ref) for i in range(1, 7)}
        rows: list[tuple[str, dict[int, float], str, str]] = [
            ('linear', e_lin, data.long_inputs(lin.model_), 'LOpInf(r) as in the study'),
            ('floor', floor, '', 'E q with the true reduced coordinates')]
        is_z = np.array([i >= E.shape[0] // 2 for i in range(E.shape[0])])  # x1..x20, z1..z20
        keep = parity_mask(lin, is_z) if args.parity else None
        if args.modes:
            modes = (tuple(range(args.modes)) if args.modes_by == 'index'
                     else amplitude_modes(data, args.modes, lin))
            keep = mode_mask(r, modes, args.mode_parts)
            if args.parity:
                par = parity_mask(lin, is_z)
                keep = (keep[0] & par[0], keep[1] & par[1])
            print(f'r = {r}: G, H ({args.mode_parts}) on coordinates {modes}: '
                  f'{int(keep[0].sum())} cubic, {int(keep[1].sum())} quartic entries')
        joint = 'all' if keep is None else 'all-masked'
        for v in variants:
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter('ignore', UserWarning)
                if v == 'library':
                    model: Any = LOpInf(r=r, forces='cubic', cubic_options=dict(
                        CUBIC_EEL_OPTIONS)).fit(ReducedData.from_arrays(
                            [data.Q[i] for i in TRAIN], [data.U[i] for i in TRAIN],
                            [data.Y[i] for i in TRAIN], data.dt, data.y_ref)).model_
                    how = f'forces=cubic, {CUBIC_EEL_OPTIONS}'
                elif v == 'correction':
                    model, how = correction(data, lin)
                elif v == 'oe':
                    model, how = oe(data, lin, 'nl', args.oe_lambda, args.oe_iters, keep=keep)
                elif v == 'oe-lin':
                    model, how = oe(data, lin, 'lin', 0.0, args.oe_iters)
                elif v == 'oe-joint':
                    model, how = oe(data, lin, joint, args.joint_lambda, args.oe_iters,
                                    keep=keep, lam_lin=args.joint_lambda)
                elif v == 'oe-lowrank':
                    model, how = oe_lowrank(data, lin, args.oe_lambda, args.oe_iters,
                                            rank=args.rank)
                elif v == 'oe-structured':
                    model, how = oe_structured(data, lin, args.joint_lambda, args.oe_iters,
                                               lam_lin=args.joint_lambda)
                elif v == 'ms-oe':
                    model, how = oe(data, lin, 'all', args.joint_lambda, args.capacity_iters,
                                    lam_lin=args.joint_lambda, window=args.window)
                elif v == 'ms-structured':
                    model, how = oe_structured(data, lin, args.joint_lambda,
                                               args.capacity_iters, lam_lin=args.joint_lambda,
                                               window=args.window)
                elif v == 'capacity-structured':
                    model, how = oe_structured(data, lin, args.oe_lambda, args.capacity_iters,
                                               eps=TRAIN + TESTS)
                elif v == 'capacity':
                    model, how = oe(data, lin, 'nl', args.oe_lambda, args.capacity_iters,
                                    eps=TRAIN + TESTS, keep=keep)
                elif v == 'capacity-joint':
                    model, how = oe(data, lin, joint, args.oe_lambda, args.capacity_iters,
                                    eps=TRAIN + TESTS, keep=keep,
                                    lam_lin=args.oe_lambda if keep is not None else 0.0)
                else:
                    model, how = oe(data, lin, 'lin', 0.0, args.capacity_iters,
                                    eps=TRAIN + TESTS)
                if v.startswith('capacity'):
                    how += ' [trained on the test episodes too]'
            how += f' ({time.perf_counter() - t0:.0f} s)'
            rows.append((v, data.dev_errors(model), data.long_inputs(model), how))
        print(f'\n### r = {r}: relative deviation error (ratio to linear); train ep1, ep2; '
              f'test ep3-6')
        print('| model | ep1 | ep2 | ' + ' | '.join(f'ep{i}' for i in TESTS)
              + ' | <= 0.5 x linear | 10 x longer inputs |')
        print('|---|---|---|' + '---|' * len(TESTS) + '---|---|')
        for name, err, longer, _how in rows:
            cells = [f'{err[i]:.3f}' for i in TRAIN]
            cells += [f'{err[i]:.3f} ({err[i] / e_lin[i]:.2f})' for i in TESTS]
            wins = sum(err[i] <= 0.5 * e_lin[i] for i in TESTS)
            print(f'| {name} | ' + ' | '.join(cells) + f' | {wins} of 4 | {longer} |')
        for name, _err, _longer, how in rows:
            print(f'- {name}: {how}')


if __name__ == '__main__':
    main()
