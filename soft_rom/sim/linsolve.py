"""The linear algebra of the eel FOM's implicit steps: the rest-system factor and PCG.

Every implicit-Euler step of :mod:`soft_rom.sim.eel` solves with the SPD rest matrix
``M + h C + h^2 K_0`` (:class:`_SPDFactor`, factored once: CHOLMOD, else LAPACK's banded
Cholesky), directly (rest tangent) or as the preconditioner of conjugate gradients
(:func:`_pcg`, corotated tangent). :func:`memory_estimate` predicts the peak memory of a
simulation from the mesh resolution alone, before anything is built.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from soft_rom.errors import ConfigError, SolverError
from soft_rom.sim.eel_types import EelConfig

__all__ = ['LINEAR_SOLVERS', 'cholmod_available', 'memory_estimate']

Array = NDArray[np.float64]

#: Linear solvers of the rest system, ``'auto'`` first (:class:`_SPDFactor`).
LINEAR_SOLVERS = ('auto', 'cholmod', 'banded')


def memory_estimate(resolution: int, solver: str = 'auto') -> tuple[int, float]:
    """``(n_dof, bytes)``: the peak memory of simulating episodes, before building the model.

    The larger of two moments, plus 200 MB of interpreter: the assembly of the rest stiffness
    (about 15 kB per DOF: its element blocks in coordinate form, then compressed), and the
    factor with the operators and work vectors (3 kB per DOF). CHOLMOD's factor has about
    ``9.5e6 (n / 32886)^1.4`` entries (measured 9.5 M, 48 M and 150 M at resolutions 2, 3
    and 4), at about 12 bytes an entry with its supernodal padding; the banded factor is
    about 3.8 cross-sections of DOFs wide (measured 395 at resolution 2, 1,355 at 4).
    Measured peak RSS (``benchmarks/bench_sim.py``): 0.28, 0.61, 1.63 and 3.52 GB (CHOLMOD)
    at resolutions 1-4, 3.70 GB (banded) at 4; estimated 0.28, 0.71, 1.81, 3.89 and 4.12 GB.
    """
    nx, ny, nz = EelConfig(resolution=resolution).grid_shape()
    section = (ny + 1) * (nz + 1)
    n_dof = 3 * (nx + 1) * section
    if solver == 'auto':
        solver = 'cholmod' if cholmod_available() else 'banded'
    if solver == 'cholmod':
        factor = 12.0 * 9.5e6 * (n_dof / 32886.0) ** 1.4
    else:
        factor = 3.8 * section * n_dof * 8.0
    return n_dof, max(15e3 * n_dof, factor + 3e3 * n_dof) + 200e6


#: Environment variables that fix the thread count of the BLAS CHOLMOD loads.
_BLAS_THREAD_VARS = ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS')


def _cholmod() -> Any:
    """``sksparse.cholmod``, its BLAS loaded with one thread (ImportError without it).

    A CHOLMOD solve is a sequence of small BLAS calls, one per supernode; a threaded BLAS
    synchronizes its threads at each, which on a loaded machine made a resolution-2 step
    13x slower in wall time than one thread (measured 2.7 s against 0.2 s, same CPU time).
    The thread count is read when the library loads, so it is set for that moment only
    (the variables are restored; a value the user set is kept).
    """
    import sys
    if 'sksparse.cholmod' in sys.modules:
        return sys.modules['sksparse.cholmod']
    import os
    saved = {k: os.environ.get(k) for k in _BLAS_THREAD_VARS}
    for k in _BLAS_THREAD_VARS:
        os.environ.setdefault(k, '1')
    try:
        import sksparse.cholmod
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return sksparse.cholmod


def cholmod_available() -> bool:
    """Whether CHOLMOD (scikit-sparse, the ``fast`` extra) can be imported."""
    try:
        _cholmod()
    except ImportError:
        return False
    return True


class _SPDFactor:
    """Cholesky factorization of the SPD rest matrix ``M + h C + h^2 K_0``, reused every step.

    ``'cholmod'``: CHOLMOD's supernodal Cholesky with its fill-reducing ordering (METIS nested
    dissection or AMD, whichever fills less), from scikit-sparse (the ``fast`` extra). At the
    paper's size (233,082 free DOFs) its factor has 150 M entries against the band's 316 M,
    and a solve reads it in BLAS blocks: measured 1.8x faster for one right-hand side
    (``benchmarks/bench_sim.py``). ``'banded'``: the nodes are numbered x-major, so the
    matrix of the slender body is banded with a half-bandwidth of about three cross-sections
    of DOFs, and LAPACK's banded Cholesky (``pbtrf``/``pbtrs``) beats SuperLU's general
    sparse LU; above ``max_bytes`` of band storage it falls back to SuperLU with a symmetric
    minimum-degree ordering. ``'auto'``: CHOLMOD when installed, else banded.
    """

    def __init__(self, A: sp.spmatrix, kind: str = 'auto', max_bytes: float = 6e9) -> None:
        if kind not in LINEAR_SOLVERS:
            raise ConfigError(f'linear solver must be one of {", ".join(LINEAR_SOLVERS)}; '
                              f'got {kind!r}.')
        if kind == 'cholmod' or (kind == 'auto' and cholmod_available()):
            self._init_cholmod(A)
            return
        coo = sp.triu(A, format='coo')
        n = A.shape[0]
        bw = int(np.max(coo.col - coo.row)) if coo.nnz else 0
        self.kind = 'banded-cholesky'
        if (bw + 1) * n * 8 <= max_bytes:
            ab = np.zeros((bw + 1, n))
            ab[bw + coo.row - coo.col, coo.col] = coo.data
            try:
                self._cb = sla.cholesky_banded(ab, lower=False, check_finite=False)
            except np.linalg.LinAlgError as err:
                raise SolverError(f'the rest system matrix is not positive definite: {err}') \
                    from err
            self.bandwidth = bw
            return
        self.kind = 'superlu'
        self._lu = spla.splu(A.tocsc(), permc_spec='MMD_AT_PLUS_A', diag_pivot_thresh=0.0,
                             options={'SymmetricMode': True})

    def _init_cholmod(self, A: sp.spmatrix) -> None:
        try:
            cholmod = _cholmod()
        except ImportError as err:
            raise ConfigError('the CHOLMOD linear solver needs scikit-sparse: pip install '
                              "'soft_rom[fast]' (with SuiteSparse, e.g. apt install "
                              'libsuitesparse-dev), or use the banded solver') from err
        self.kind = 'cholmod'
        try:
            self._chol = cholmod.cholesky(sp.csc_matrix(A), mode='supernodal')
        except cholmod.CholmodNotPositiveDefiniteError as err:
            raise SolverError(f'the rest system matrix is not positive definite: {err}') \
                from err

    def solve(self, b: Array) -> Array:
        """``A^{-1} b`` for ``b`` of shape (n,) or (n, k)."""
        if self.kind == 'cholmod':
            return np.asarray(self._chol.solve_A(b))
        if self.kind == 'superlu':
            return self._lu.solve(b)
        return sla.cho_solve_banded((self._cb, False), b, check_finite=False)


def _pcg(apply_A: Callable[[NDArray], NDArray], precond: Callable[[NDArray], NDArray],
         b: Array, x0: Array, rtol: float, maxiter: int) -> tuple[Array, int, float]:
    """Preconditioned CG from ``x0``; returns ``(x, iterations, relative residual)``."""
    x = x0.copy()
    r = b - apply_A(x)
    bnorm = float(np.linalg.norm(b)) or 1.0
    res = float(np.linalg.norm(r)) / bnorm
    if res <= rtol:
        return x, 0, res
    z = precond(r)
    p = z.copy()
    rz = float(r @ z)
    for it in range(1, maxiter + 1):
        Ap = apply_A(p)
        a = rz / float(p @ Ap)
        x += a * p
        r -= a * Ap
        res = float(np.linalg.norm(r)) / bnorm
        if res <= rtol:
            return x, it, res
        z = precond(r)
        rz_new = float(r @ z)
        p = z + (rz_new / rz) * p
        rz = rz_new
    return x, maxiter, res
