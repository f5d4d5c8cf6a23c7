"""Linear model predictive control of a ROM's outputs (condensed, warm-started QP).

At each control step ``h`` (a whole multiple of the model's ``dt``; the exact zero-order-hold
discretization :meth:`~soft_rom.models.LinearROM.discretize`) the MPC chooses the inputs of
the next ``N`` steps,

.. math::

    \\min_{u_0..u_{N-1}} \\sum_{j=1}^{N} \\frac{w_y}{p} \\Big\\| \\frac{\\hat y_j - r_j}{s_y}
    \\Big\\|^2 + \\sum_{j=0}^{N-1} \\frac{w_{\\Delta}}{m} \\| v_j - v_{j-1} \\|^2
    + \\frac{w_0}{m} \\| P_0 v_j \\|^2

    x_{j+1} = A x_j + B u_j, \\quad \\hat y_j = C x_j + D u_j + d + y_{ref}, \\quad
    u_j = c + S v_j, \\quad -1 \\le v_j \\le 1, \\quad |v_j - v_{j-1}| \\le \\delta,

where ``v`` are the inputs scaled to the box ``[u_min, u_max]`` (centre ``c``, half-width
``S``), ``s_y`` the output scale (the training data's largest output deviation), ``d`` the
estimated output disturbance (:mod:`soft_rom.control.estimator`; held over the horizon,
which makes the loop offset-free), ``v_{-1}`` the input applied last and ``δ`` the rate
bound per step. ``P_0`` projects onto the input directions that the model's steady-state
gain does not see (for the eel's antagonistic training data: both chambers of a segment
pressurised together); a small weight there keeps the MPC from driving the plant where the
model knows nothing, and changes nothing the model can see, so tracking stays offset-free.

The states are eliminated (condensed form): the Hessian ``H`` (``N m`` square) and the
constraint matrix are fixed and factorized once; each step forms the linear term from the
state, disturbance, reference and last input, and solves with the warm-started solver of
:mod:`soft_rom.control.qp`. Only the first input is applied (receding horizon).

The cubic LOpInf (nonlinear restoring force) is refused: the MPC is linear. A model that
cannot be trusted (``model.trust_issues()``: unstable, absurd gain, ...) is controlled all
the same, with an :class:`~soft_rom.errors.UntrustedModelWarning` (once per model).
"""

from __future__ import annotations

from dataclasses import dataclass
import math
from typing import Any
import weakref

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.control.qp import make_solver, QPResult
from soft_rom.envelope import check_bound_units
from soft_rom.errors import ConfigError, DimensionError, UntrustedModelWarning, warn

__all__ = ['MPC', 'MPCConfig', 'MPCStep', 'TERMINAL_COSTS', 'input_bounds', 'require_linear',
           'warn_untrusted']

Array = NDArray[np.float64]

TERMINAL_COSTS = ('riccati', 'none')

#: The untrusted models already warned about (each once).
_WARNED: weakref.WeakSet[Any] = weakref.WeakSet()


@dataclass(frozen=True)
class MPCConfig:
    """Settings of the MPC (SI units).

    Parameters
    ----------
    step : float
        Control step ``h`` (s); a whole multiple of the model's ``dt`` (default 10 ms).
    horizon : float
        Prediction horizon (s), ``N = round(horizon / step)`` steps (default 0.2 s).
    output_weight : float
        ``w_y``: weight of the output error (mean over outputs, scaled by ``s_y``).
    rate_weight : float
        ``w_Δ``: weight of the scaled input increments (mean over inputs); default 1e-4, the
        weight the control study chooses on its training reference (the geometric mean of
        the four controllers' errors; ``docs/control.md``), which also settles the static
        bend better than 1e-3. The CLI and the controller node take this default.
    null_weight : float
        ``w_0``: weight of the inputs in the directions the model's steady-state gain does
        not see.
    u_min, u_max : tuple of float, optional
        Input bounds (one value per input, or one for all); default the training range
        recorded in the model file (``metadata['envelope']``).
    rate_max : float or tuple of float, optional
        Largest input change per second (one value for all inputs, or one per input, in
        input units per s);
        default: the full range ``u_max - u_min`` in 50 ms.
    solver : str
        ``'daqp'`` (default) or ``'osqp'``.
    terminal : str
        ``'none'`` (default): the horizon's stage costs only; ``'riccati'``: a terminal cost
        on the state at the end of the horizon, the cost-to-go of the same stage cost over an
        infinite horizon (the discrete algebraic Riccati equation of the ROM), about the
        steady state that best reaches the reference.
    """

    step: float = 0.01
    horizon: float = 0.2
    output_weight: float = 1.0
    rate_weight: float = 1e-4
    null_weight: float = 1e-2
    u_min: tuple[float, ...] | None = None
    u_max: tuple[float, ...] | None = None
    rate_max: float | tuple[float, ...] | None = None
    solver: str = 'daqp'
    terminal: str = 'none'

    def __post_init__(self) -> None:
        for name in ('step', 'horizon'):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ConfigError(f'MPC {name} must be a positive number of seconds; got {v!r}.')
        for name in ('output_weight', 'rate_weight', 'null_weight'):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ConfigError(f'MPC {name} must be a finite number >= 0; got {v!r}.')
        if self.output_weight <= 0:
            raise ConfigError('MPC output_weight must be > 0 (nothing would be tracked).')
        if self.rate_max is not None:
            try:
                rate = np.asarray(self.rate_max, dtype=np.float64).reshape(-1)
            except (TypeError, ValueError):
                rate = np.zeros(0)
            if not (rate.size and np.all(np.isfinite(rate)) and np.all(rate > 0)):
                raise ConfigError(f'MPC rate_max must be one number > 0, or one per input; '
                                  f'got {self.rate_max!r}.')
        if self.terminal not in TERMINAL_COSTS:
            raise ConfigError(f'MPC terminal cost {self.terminal!r} is not one of '
                              f'{", ".join(TERMINAL_COSTS)}.')
        if self.horizon < self.step * (1 - 1e-9):
            raise ConfigError(f'MPC horizon {self.horizon:g} s is shorter than one step '
                              f'({self.step:g} s).')


def input_bounds(model: Any, u_min: ArrayLike | None = None,
                 u_max: ArrayLike | None = None) -> tuple[Array, Array]:
    """Input bounds: given, else the training range in the model file.

    Returns
    -------
    lo, hi : ndarray, shape (m,)

    Raises
    ------
    ConfigError
        No bound given and none recorded, or a bound that is not finite or ``lo >= hi``.
    """
    m = int(model.n_inputs)
    env = model.metadata.get('envelope') if isinstance(model.metadata, dict) else None
    env = env if isinstance(env, dict) else {}

    def side(value: ArrayLike | None, key: str, flag: str) -> Array:
        if value is None:
            value = env.get(key)
            if not value:
                raise ConfigError(f'the model file records no training input range; give the '
                                  f'input bounds ({flag}).')
        a = np.array(value, dtype=np.float64).reshape(-1)
        if a.size == 1:
            a = np.full(m, a[0])
        if a.size != m:
            raise ConfigError(f'{flag} needs 1 or {m} values (one per input); got {a.size}.')
        if not np.all(np.isfinite(a)):
            raise ConfigError(f'{flag} must be finite; got {a.tolist()}.')
        return a

    lo, hi = side(u_min, 'u_min', '--u-min'), side(u_max, 'u_max', '--u-max')
    if np.any(lo >= hi):
        i = int(np.argmax(lo >= hi))
        raise ConfigError(f'input bounds: u_min >= u_max for input {i} ({lo[i]:g} >= '
                          f'{hi[i]:g}); give u_min below u_max.')
    if (u_min is not None or u_max is not None) and env.get('u_min') and env.get('u_max'):
        check_bound_units(model, lo, hi, env['u_min'], env['u_max'], 'input bounds')
    return lo, hi


def require_linear(model: Any, what: str) -> None:
    """Refuse a model ``what`` (the MPC, a plant, an estimator) cannot take as linear."""
    if getattr(model, 'is_nonlinear', False) or getattr(model, 'is_linear', True) is False:
        raise ConfigError(
            f'{getattr(model, "method", "this")} model is nonlinear (cubic LOpInf): {what} is '
            'linear; fit a linear LOpInf (soft-rom fit --forces linear) to control with.')
    if not callable(getattr(model, 'discretize', None)):
        raise ConfigError(f'{type(model).__name__} cannot be discretized; {what} needs a '
                          'linear ROM (LOpInf, DMDc, ERA/OKID).')


def warn_untrusted(model: Any) -> None:
    """An :class:`UntrustedModelWarning` naming why, once per model that cannot be trusted."""
    issues = model.trust_issues() if callable(getattr(model, 'trust_issues', None)) else []
    if not issues or model in _WARNED:
        return
    _WARNED.add(model)
    warn(f'{getattr(model, "method", "the")} r={getattr(model, "r", "?")} model is not '
         f'trusted: {"; ".join(issues)}; the MPC controls with it all the same (its '
         'predictions, and so its commands, may be wrong).', UntrustedModelWarning)


@dataclass(frozen=True)
class MPCStep:
    """One MPC solve.

    Attributes
    ----------
    u : ndarray, shape (m,)
        The input to apply now (in bounds; the last one, clipped, when the QP failed).
    plan : ndarray, shape (m, N) or None
        The optimal input sequence.
    qp : QPResult
    saturated : int
        Inputs of ``u`` at a bound.
    """

    u: Array
    plan: Array | None
    qp: QPResult
    saturated: int


class MPC:
    """Linear MPC of a :class:`~soft_rom.models.LinearROM`'s outputs.

    Parameters
    ----------
    model : LinearROM
        LOpInf (continuous, discretized exactly at ``config.step``), DMDc or ERA/OKID
        (discrete: ``config.step`` a whole multiple of their ``dt``).
    config : MPCConfig

    Attributes
    ----------
    h : float
        Control step (s).
    N : int
        Horizon in steps.
    system : DiscreteSystem
        The model at step ``h``.
    lo, hi : ndarray, shape (m,)
        Input bounds.
    rate : ndarray, shape (m,)
        Largest input change per step.
    y_scale : float
        ``s_y`` (output units).
    """

    def __init__(self, model: Any, config: MPCConfig | None = None) -> None:
        cfg = config or MPCConfig()
        require_linear(model, 'the MPC')
        warn_untrusted(model)
        ratio = cfg.step / float(model.dt)
        j = int(round(ratio))
        if j < 1 or abs(ratio - j) > 1e-6:
            raise ConfigError(f'the control step {cfg.step:g} s must be a whole multiple of the '
                              f'model time step {model.dt:g} s (e.g. {max(j, 1) * model.dt:g} s).')
        self.model = model
        self.config = cfg
        self.h = j * float(model.dt)
        self.N = max(1, int(round(cfg.horizon / self.h)))
        self.system = model.discretize(self.h)
        A, B, C, D, _ = self.system
        self.n, self.m, self.p = A.shape[0], B.shape[1], C.shape[0]
        self.lo, self.hi = input_bounds(model, cfg.u_min, cfg.u_max)
        self.centre = 0.5 * (self.lo + self.hi)
        self.half = 0.5 * (self.hi - self.lo)
        if cfg.rate_max is None:
            rate = 2 * self.half / 0.05
        else:
            rate = np.asarray(cfg.rate_max, dtype=np.float64).reshape(-1)
            if rate.size not in (1, self.m):
                raise ConfigError(f'MPC rate_max needs 1 or {self.m} values (one per input); '
                                  f'got {rate.size}.')
        self.rate = np.broadcast_to(rate, (self.m,)) * self.h
        env = model.metadata.get('envelope') if isinstance(model.metadata, dict) else None
        dev = env.get('y_dev_max') if isinstance(env, dict) else None
        self.y_scale = float(dev) if isinstance(dev, (int, float)) and dev and dev > 0 else \
            max(float(np.max(np.abs(model.y_ref))), 1.0)
        self._build()
        self.solver = make_solver(cfg.solver, self.H, self.A_rate)
        self.v_last: Array | None = None

    # -- construction -------------------------------------------------------------------
    def _build(self) -> None:
        A, B, C, D, _ = self.system
        n, m, p, N = self.n, self.m, self.p, self.N
        S = np.diag(self.half)
        # impulse blocks C A^k B, k = 0..N-1, and the state-to-output blocks C A^j, j = 1..N
        CAk = []
        M = C.copy()
        for _ in range(N):
            CAk.append(M)
            M = M @ A
        Phi = np.zeros((N * p, n))
        G = np.zeros((N * p, N * m))                     # outputs 1..N from inputs 0..N-1
        P = C @ A
        for j in range(1, N + 1):
            Phi[(j - 1) * p:j * p] = P
            P = P @ A
            for i in range(j):
                G[(j - 1) * p:j * p, i * m:(i + 1) * m] = CAk[j - 1 - i] @ B
            i_d = min(j, N - 1)                          # y_j sees u_j (u_N = u_{N-1})
            G[(j - 1) * p:j * p, i_d * m:(i_d + 1) * m] += D
        if not (np.all(np.isfinite(G)) and np.all(np.isfinite(Phi))):
            raise ConfigError(f'the {self.model.method} model overflows over a '
                              f'{N * self.h:g} s horizon; shorten the horizon.')
        Gs = G @ np.kron(np.eye(N), S)                  # in scaled inputs v
        wy = self.config.output_weight / (p * self.y_scale ** 2)
        wd = self.config.rate_weight / m
        # Input directions the steady-state gain does not see.
        gain = self.steady_gain() @ S
        _U, sv, Vt = np.linalg.svd(gain)
        weak = np.ones(m, dtype=bool)
        if sv.size and sv[0] > 0:
            weak[:sv.size] = sv < 1e-3 * sv[0]
        V = Vt.T
        P0 = V[:, weak] @ V[:, weak].T
        w0 = self.config.null_weight / m
        Dlt = np.eye(N * m) - np.eye(N * m, k=-m)       # v_j - v_{j-1}
        H = wy * Gs.T @ Gs + wd * Dlt.T @ Dlt + w0 * np.kron(np.eye(N), P0)
        self._Fx = wy * Gs.T @ Phi                      # linear term per unit state
        self._Fe = wy * Gs.T                            # per unit output offset (stacked)
        self._Fc = G @ np.tile(self.centre, N)          # outputs of the centre input
        self._Fv = wd * Dlt.T[:, :m]                    # from v_{-1}
        self.H_inputs = wd * Dlt.T @ Dlt + w0 * np.kron(np.eye(N), P0)   # (benchmarks)
        self.terminal = 'none'
        self._term: tuple[Array, ...] | None = None
        if self.config.terminal == 'riccati':
            H = H + self._terminal_cost(wy, wd, w0, P0, S)
        H += 1e-10 * np.trace(H) / (N * m) * np.eye(N * m)   # strictly convex
        self.H = 0.5 * (H + H.T)
        self.A_rate = Dlt
        self.weak_inputs = int(weak.sum())

    def _terminal_cost(self, wy: float, wd: float, w0: float, P0: Array, S: Array) -> Array:
        """The Riccati terminal cost's Hessian block; keeps what :meth:`qp_data` needs.

        The stage cost continued past the horizon, in deviations from a steady state
        ``(x_s, v_s)``: state ``z = (x - x_s, v_{j-1} - v_s)``, decision the increment
        ``δ = v_j - v_{j-1}``,

            z⁺ = [[A, B S], [0, I]] z + [[B S], [I]] δ,
            ℓ = w_y ‖C (x - x_s) + D S (v - v_s)‖² + w_Δ ‖δ‖² + w_0 ‖P₀ (v - v_s)‖²,

        whose infinite-horizon optimal cost is ``zᵀ P z`` (``scipy.linalg.solve_discrete_are``
        with the cross term). At the end of the horizon, ``zᵀ P z`` less the output term the
        horizon already counts is the terminal cost: a 0.2 s horizon then weighs what the
        inputs do to the seconds after it (the eel's lightly damped first mode), and
        without active bounds the first move is that of the infinite-horizon optimum
        (exactly, for a model without feedthrough). ``v_s`` is the steady input whose
        outputs best reach the reference at the horizon's end (least squares with the same
        weights), ``x_s`` its steady state; both are linear in the reference and the
        disturbance, so the QP stays a QP with a fixed Hessian. A model with no stabilizing
        solution (an unstable mode the inputs cannot reach) keeps no terminal cost
        (:attr:`terminal` says why).
        """
        import scipy.linalg as sla
        A, B, C, D, _ = self.system
        n, m, N = self.n, self.m, self.N
        BS, DS = B @ S, D @ S
        Aa = np.block([[A, BS], [np.zeros((m, n)), np.eye(m)]])
        Ba = np.vstack([BS, np.eye(m)])
        Ca = np.hstack([C, DS])                         # outputs of z (with v_{j-1})
        Qa = wy * Ca.T @ Ca
        Qa[n:, n:] += w0 * P0
        Ra = wy * DS.T @ DS + (wd + w0 * 1e-6) * np.eye(m) + w0 * P0
        Sa = wy * Ca.T @ DS
        Sa[n:] += w0 * P0
        try:
            P = sla.solve_discrete_are(Aa, Ba, Qa, Ra, s=Sa)
            if not np.all(np.isfinite(P)):
                raise np.linalg.LinAlgError('non-finite solution')
        except (np.linalg.LinAlgError, ValueError) as err:
            self.terminal = f'none (no stabilizing Riccati solution: {err})'
            return np.zeros((N * m, N * m))
        # the horizon already counts the output at its end: the terminal weight is the rest
        # of the cost-to-go (positive semi-definite: every other stage term is a square)
        P = 0.5 * (P + P.T) - wy * Ca.T @ Ca
        # end state x_N = A^N x_0 + sum_i A^(N-1-i) B (c + S v_i); z_N = E v + (free part)
        Gam = np.zeros((n, N * m))
        M = B.copy()
        for i in range(N - 1, -1, -1):
            Gam[:, i * m:(i + 1) * m] = M
            M = A @ M
        E = np.zeros((n + m, N * m))
        E[:n] = Gam @ np.kron(np.eye(N), S)
        E[n:, (N - 1) * m:] = np.eye(m)
        # steady state: v_s = K (r - d - y_ref - G c), x_s = X (c + S v_s)
        X = np.linalg.lstsq(np.eye(n) - A, B, rcond=None)[0]
        gain = (C @ X + D) @ S
        K = np.linalg.solve(wy * gain.T @ gain + w0 * P0 + 1e-12 * np.eye(m), wy * gain.T)
        self._term = (np.linalg.matrix_power(A, N), Gam @ np.tile(self.centre, N), X,
                      K, (C @ X + D) @ self.centre, E.T @ P)
        self.terminal = 'riccati'
        return E.T @ P @ E

    def steady_gain(self) -> Array:
        """``(p, m)``: the outputs' steady-state deviation per unit input held."""
        A, B, C, D, _ = self.system
        try:
            return C @ np.linalg.solve(np.eye(self.n) - A, B) + D
        except np.linalg.LinAlgError:
            return C @ np.linalg.lstsq(np.eye(self.n) - A, B, rcond=None)[0] + D

    # -- solving ------------------------------------------------------------------------
    def scale(self, u: ArrayLike) -> Array:
        """Inputs in the scaled box coordinates ``v = (u - c) / S``."""
        return (np.asarray(u, dtype=np.float64) - self.centre) / self.half

    def unscale(self, v: ArrayLike) -> Array:
        """Inputs from scaled coordinates, ``u = c + S v``."""
        return self.centre + self.half * np.asarray(v, dtype=np.float64)

    def solve(self, x: ArrayLike, d: ArrayLike, reference: ArrayLike,
              u_last: ArrayLike) -> MPCStep:
        """The input to apply now.

        Parameters
        ----------
        x : ndarray, shape (n,)
            State estimate (deviation coordinates) at the current control time.
        d : ndarray, shape (p,)
            Output disturbance estimate (held over the horizon).
        reference : ndarray, shape (p, N)
            Absolute reference outputs at the next ``N`` control times ``t + h .. t + N h``.
        u_last : ndarray, shape (m,)
            The input applied over the last step (the origin of the rate bounds).

        Returns
        -------
        MPCStep
            When the QP is infeasible or fails, ``u`` is :meth:`fallback` (``u_last`` held,
            clipped into the bounds) and ``plan`` is ``None``.
        """
        N, m = self.N, self.m
        f, lb, ub, lbA, ubA = self.qp_data(x, d, reference, u_last)
        if not (np.all(np.isfinite(f)) and np.all(np.isfinite(lbA))):
            res = QPResult(None, 'failed', 0, 0.0, 'non-finite QP data')
        else:
            res = self.solver.solve(f, lb, ub, lbA, ubA)
        if res.ok and res.x is not None:
            v = np.clip(res.x.reshape(N, m), -1.0, 1.0)
            plan = self.unscale(v).T
            u = np.clip(plan[:, 0], self.lo, self.hi)
            self.v_last = v[0]
        else:
            plan = None
            u = self.fallback(u_last)
        saturated = int(np.count_nonzero((u <= self.lo + 1e-9 * self.half)
                                         | (u >= self.hi - 1e-9 * self.half)))
        return MPCStep(u=u, plan=plan, qp=res, saturated=saturated)

    def qp_data(self, x: ArrayLike, d: ArrayLike, reference: ArrayLike,
                u_last: ArrayLike) -> tuple[Array, Array, Array, Array, Array]:
        """``(f, lb, ub, lbA, ubA)`` of the QP for the arguments of :meth:`solve`."""
        N, m, p = self.N, self.m, self.p
        x = np.asarray(x, dtype=np.float64)
        d = np.asarray(d, dtype=np.float64)
        R = np.asarray(reference, dtype=np.float64)
        u_last = np.asarray(u_last, dtype=np.float64)
        if x.shape != (self.n,) or d.shape != (p,) or R.shape != (p, N) or u_last.shape != (m,):
            raise DimensionError(
                f'MPC.solve needs x ({self.n},), d ({p},), reference ({p}, {N}), u_last ({m},);'
                f' got {x.shape}, {d.shape}, {R.shape}, {u_last.shape}.')
        v_last = self.scale(u_last)
        offset = (self._Fc + np.tile(d + self.model.y_ref, N)
                  - (R.T.reshape(-1)))                   # stacked over j = 1..N
        f = self._Fx @ x + self._Fe @ offset - self._Fv @ v_last
        if self._term is not None:
            AN, free_c, X, K, y_c, EP = self._term
            v_s = K @ (R[:, -1] - d - self.model.y_ref - y_c)
            x_s = X @ (self.centre + self.half * v_s)
            f = f + EP[:, :self.n] @ (AN @ x + free_c - x_s) - EP[:, self.n:] @ v_s
        dv = self.rate / self.half
        lbA = np.tile(-dv, N)
        ubA = np.tile(dv, N)
        lbA[:m] += v_last
        ubA[:m] += v_last
        ones = np.ones(N * m)
        return f, -ones, ones.copy(), lbA, ubA

    def fallback(self, u_last: ArrayLike) -> Array:
        """The safe command: ``u_last`` held, clipped into the bounds.

        A ``u_last`` of the wrong size or not finite is replaced by the centre of the bounds.
        """
        u_last = np.array(u_last, dtype=np.float64).reshape(-1)
        if u_last.shape != (self.m,) or not np.all(np.isfinite(u_last)):
            return self.centre.copy()
        return np.clip(u_last, self.lo, self.hi)
