"""QP solvers for the MPC: one small interface over solvers made for MPC (DAQP, OSQP).

The MPC solves the same dense quadratic program every control step with a new linear term
and new rate bounds:

.. math::

    \\min_z \\tfrac12 z^T H z + f^T z \\quad \\text{s.t.} \\quad
    l \\le z \\le u, \\qquad l_A \\le A z \\le u_A,

with ``H`` and ``A`` fixed. A :class:`QPSolver` is built once from ``(H, A)`` (factorized
there) and then solves for ``(f, l, u, l_A, u_A)``, warm-started from the previous solve.

* :class:`DaqpSolver` (default) -- DAQP, a dual active-set solver for small dense QPs
  (Arnström, Bemporad & Axehill 2022); its workspace keeps the factorization of ``H`` and
  the last active set (the warm start), and simple bounds are handled apart from ``A``.
* :class:`OsqpSolver` -- OSQP (ADMM; Stellato et al. 2020), installed with cvxpy; warm
  started from the previous primal and dual solution.

Which is faster on the eel's MPC, and by how much against cvxpy, is measured by
``benchmarks/bench_mpc.py`` (the numbers are in ``docs/control.md``).
"""

from __future__ import annotations

from dataclasses import dataclass
import time
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from soft_rom.errors import ConfigError

__all__ = ['DaqpSolver', 'OsqpSolver', 'QPResult', 'QPSolver', 'SOLVERS', 'make_solver']

Array = NDArray[np.float64]


@dataclass(frozen=True)
class QPResult:
    """What one solve returned.

    Attributes
    ----------
    x : ndarray, shape (n,) or None
        The solution (``None`` when the solver found none).
    status : str
        ``'optimal'``, ``'infeasible'`` or ``'failed'`` (iteration limit, numerical trouble).
    iterations : int
    seconds : float
        Wall time of the solve call.
    detail : str
        The solver's own status, for diagnostics.
    """

    x: Array | None
    status: str
    iterations: int
    seconds: float
    detail: str = ''

    @property
    def ok(self) -> bool:
        """Whether an optimal solution came back."""
        return self.status == 'optimal' and self.x is not None


class QPSolver(Protocol):
    """A warm-started solver of one QP family with fixed ``H`` and ``A``."""

    name: str

    def solve(self, f: Array, lb: Array, ub: Array, lbA: Array, ubA: Array) -> QPResult:
        """Solve with the given linear term and bounds (warm-started from the last solve)."""

    def reset(self) -> None:
        """Forget the warm start."""


class DaqpSolver:
    """DAQP (dual active set) with a persistent workspace.

    Parameters
    ----------
    H : ndarray, shape (n, n)
        Positive definite Hessian.
    A : ndarray, shape (mA, n)
        General constraint matrix (the simple bounds are separate).
    iter_limit : int
        Iteration cap (a solve that reaches it is ``'failed'``).
    """

    name = 'daqp'

    def __init__(self, H: Array, A: Array, *, iter_limit: int = 1000) -> None:
        import daqp  # noqa: F401 -- fail here, at construction, when it is missing
        self.H = np.ascontiguousarray(H, dtype=np.float64)
        self.A = np.ascontiguousarray(A, dtype=np.float64)
        self.n = self.H.shape[0]
        self.iter_limit = int(iter_limit)
        self._model: Any = None

    def reset(self) -> None:
        self._model = None

    def solve(self, f: Array, lb: Array, ub: Array, lbA: Array, ubA: Array) -> QPResult:
        bu = np.concatenate([ub, ubA])
        bl = np.concatenate([lb, lbA])
        f = np.ascontiguousarray(f, dtype=np.float64)
        t0 = time.perf_counter()
        if self._model is None:
            import daqp
            model = daqp.Model()
            model.settings = {'iter_limit': self.iter_limit}
            flag, _ = model.setup(self.H, f, self.A, bu, bl, np.zeros(bu.size, dtype=np.int32))
            if flag < 0:
                return QPResult(None, 'failed', 0, time.perf_counter() - t0,
                                f'daqp setup exit flag {flag}')
            self._model = model
        else:
            model = self._model
            model.update(f=f, bupper=bu, blower=bl)
        x, _fval, flag, info = model.solve()
        seconds = time.perf_counter() - t0
        iterations = int(info.get('iterations', 0))
        if flag == 1 or flag == 2:      # optimal; soft-optimal
            return QPResult(np.array(x, dtype=np.float64), 'optimal', iterations, seconds,
                            f'daqp exit flag {flag}')
        self._model = None              # start the next solve cold
        status = 'infeasible' if flag == -1 else 'failed'
        return QPResult(None, status, iterations, seconds, f'daqp exit flag {flag}')


class OsqpSolver:
    """OSQP (operator splitting) on the dense problem, warm-started.

    Parameters
    ----------
    H, A : ndarray
        As for :class:`DaqpSolver`; bounds are stacked as identity rows on ``A``.
    eps : float
        Absolute and relative tolerance.
    max_iter : int
    """

    name = 'osqp'

    def __init__(self, H: Array, A: Array, *, eps: float = 1e-6, max_iter: int = 4000) -> None:
        import osqp  # noqa: F401 -- fail here, at construction, when it is missing
        import scipy.sparse as sp
        n = H.shape[0]
        self.n = n
        self._P = sp.csc_matrix(np.triu(H))
        self._A = sp.csc_matrix(np.vstack([np.eye(n), A]))
        self._settings = dict(eps_abs=eps, eps_rel=eps, max_iter=max_iter, verbose=False,
                              polish=False, warm_starting=True)
        self._solver: Any = None

    def reset(self) -> None:
        self._solver = None

    def solve(self, f: Array, lb: Array, ub: Array, lbA: Array, ubA: Array) -> QPResult:
        lo = np.concatenate([lb, lbA])
        hi = np.concatenate([ub, ubA])
        t0 = time.perf_counter()
        if self._solver is None:
            import osqp
            solver = osqp.OSQP()
            solver.setup(P=self._P, q=f, A=self._A, l=lo, u=hi, **self._settings)
            self._solver = solver
        else:
            solver = self._solver
            solver.update(q=f, l=lo, u=hi)
        res = solver.solve()
        seconds = time.perf_counter() - t0
        text = str(res.info.status)
        iterations = int(res.info.iter)
        if text == 'solved':
            return QPResult(np.array(res.x, dtype=np.float64), 'optimal', iterations, seconds,
                            text)
        self._solver = None
        status = 'infeasible' if 'infeasible' in text and 'inaccurate' not in text else 'failed'
        return QPResult(None, status, iterations, seconds, f'osqp: {text}')


SOLVERS = {'daqp': DaqpSolver, 'osqp': OsqpSolver}


def make_solver(name: str, H: Array, A: Array) -> QPSolver:
    """The solver called ``name`` (``'daqp'`` or ``'osqp'``) for fixed ``H`` and ``A``."""
    try:
        cls = SOLVERS[name]
    except KeyError:
        raise ConfigError(f'unknown QP solver {name!r}; choose one of '
                          f'{", ".join(sorted(SOLVERS))}.') from None
    try:
        return cls(H, A)
    except ImportError as err:
        raise ConfigError(f'QP solver {name!r} is not installed ({err}); pip install '
                          f'{name}') from err
