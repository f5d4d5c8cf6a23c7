"""The model interface every ROM implements: step, simulate, discretize, trust, save, load.

:class:`LinearROM` is the interface; :class:`DiscreteSystem` a discrete state-space system and
:func:`run_states` the one simulation loop. The families are in :mod:`soft_rom.models.linear`
(:class:`~soft_rom.models.linear.SecondOrderModel`, LOpInf;
:class:`~soft_rom.models.linear.DiscreteModel`, DMDc and ERA/OKID) and
:mod:`soft_rom.models.cubic` (the cubic LOpInf model).

Models know nothing of how they were made (no training arrays); they carry matrices,
offsets, names/units and JSON metadata. States are deviations from the reference
configuration; outputs are returned in absolute coordinates.

Model files are ``.npz`` archives of plain numeric arrays plus one JSON document stored as
a ``uint8`` array; they are read with ``allow_pickle=False`` and validated (format
version, sizes, shapes, finite and plausible values, dtypes) before any model is built, by
the bounded reader of :mod:`soft_rom.models.files`. See
:func:`load_model`.

A model that loads may still not deserve trust (unstable, indefinite stiffness or damping,
absurd offsets or gain): :meth:`LinearROM.trust_issues` says why;
``load_model(..., strict=True)`` refuses such models.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
import json
import os
from pathlib import Path
from typing import Any, cast, ClassVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from soft_rom.data import all_finite, as_signal, check_finite, step_length
from soft_rom.errors import DimensionError, ModelFileError
from soft_rom.gain import gain_issue
from soft_rom.models.archive import json_safe, valid_text
from soft_rom.models.files import _META_KEY, FORMAT_NAME, FORMAT_VERSION, MAX_STATES, read_model

__all__ = ['ABSURD_OFFSET', 'DiscreteSystem', 'LinearROM', 'TRUST_TOL', 'load_model', 'run_states']

#: Relative tolerance of the trust checks (spectral radius, definiteness, symmetry).
TRUST_TOL = 1e-6
#: Output offsets larger than this (in output units) are reported as absurd.
ABSURD_OFFSET = 1e6

Array = NDArray[np.float64]


class DiscreteSystem:
    """A discrete-time state-space system in deviation coordinates.

    .. math:: x_{k+1} = A x_k + B u_k, \\qquad y_k - y_{ref} = C x_k + D u_k

    Parameters
    ----------
    A : ndarray, shape (n, n)
    B : ndarray, shape (n, m)
    C : ndarray, shape (p, n)
    D : ndarray, shape (p, m)
    dt : float
        Sample time in seconds.
    """

    __slots__ = ('A', 'B', 'C', 'D', 'dt')

    def __init__(self, A: Array, B: Array, C: Array, D: Array, dt: float) -> None:
        self.A, self.B, self.C, self.D, self.dt = A, B, C, D, float(dt)

    def __iter__(self):  # allows ``A, B, C, D, dt = system``
        return iter((self.A, self.B, self.C, self.D, self.dt))


def run_states(A: Array, B: Array, x0: Array, U: Array) -> Array:
    """States ``x_0 .. x_k`` of ``x_{j+1} = A x_j + B u_j`` for inputs ``U``: the one loop.

    Parameters
    ----------
    A : ndarray, shape (n, n)
    B : ndarray, shape (n, m)
    x0 : ndarray, shape (n,)
    U : ndarray, shape (m, k)

    Returns
    -------
    X : ndarray, shape (n, k + 1)
    """
    k = U.shape[1]
    X = np.empty((A.shape[0], k + 1))
    BU = B @ U
    x = x0
    for j in range(k):
        X[:, j] = x
        x = A @ x + BU[:, j]
    X[:, k] = x
    return X


def _arr(name: str, value: ArrayLike, shape: tuple[int, ...] | None = None) -> Array:
    a = np.array(value, dtype=np.float64, copy=True)
    if shape is not None and a.shape != shape:
        raise DimensionError(f'{name} must have shape {shape}; got {a.shape}.')
    if not all_finite(a):
        raise DimensionError(f'{name} contains NaN or Inf.')
    a.setflags(write=False)
    return a


def _leading(name: str, value: ArrayLike, n: int) -> Array:
    """``value`` as float64 with ``n`` rows (a vector, or ``n`` x ``k`` for ``k`` at once)."""
    a = np.asarray(value, dtype=np.float64)
    if a.ndim not in (1, 2) or a.shape[0] != n:
        raise DimensionError(f'{name} must have shape ({n},) (or ({n}, k)); got shape '
                             f'{a.shape}.')
    return a


def _state_and_input(x: ArrayLike, u: ArrayLike, n: int, m: int) -> tuple[Array, Array]:
    """``x`` (n,) with ``u`` (m,), or ``x`` (n, k) with ``u`` (m, k): never mixed.

    Mixed shapes broadcast into nonsense (``x`` (n,) with ``u`` (m, 1) gives an (n, n)
    "state"), so they are refused.
    """
    xs, us = _leading('x', x, n), _leading('u', u, m)
    if xs.shape[1:] != us.shape[1:]:
        raise DimensionError(f'x has shape {xs.shape} and u {us.shape}: give both as vectors '
                             f'(({n},) and ({m},)) or both with k columns (({n}, k) and '
                             f'({m}, k)).')
    return xs, us


def _state_input_output(square: tuple[str, ArrayLike], inp: tuple[str, ArrayLike],
                        out: tuple[str, ArrayLike]) -> tuple[Array, Array, Array, int]:
    """The constructors' shape checks: ``square (r, r)``, ``inp (r, m)``, ``out (p, r)``."""
    (sn, S), (bn, B), (on, O) = square, inp, out
    S = np.asarray(S, dtype=np.float64)
    if S.ndim != 2 or S.shape[0] != S.shape[1]:
        raise DimensionError(f'{sn} must be square (r, r); got shape {S.shape}.')
    r = S.shape[0]
    B, O = np.asarray(B, dtype=np.float64), np.asarray(O, dtype=np.float64)
    if B.ndim != 2 or B.shape[0] != r:
        raise DimensionError(f'{bn} must have shape ({r}, m); got {B.shape}.')
    if O.ndim != 2 or O.shape[1] != r:
        raise DimensionError(f'{on} must have shape (p, {r}); got {O.shape}.')
    return S, B, O, r


def _eigvals(A: Array) -> NDArray[np.complex128]:
    """Eigenvalues of ``A``; :class:`DimensionError` when LAPACK cannot compute them."""
    try:
        with np.errstate(all='ignore'):
            ev = np.linalg.eigvals(A)
    except (np.linalg.LinAlgError, ValueError) as err:
        raise DimensionError(f'eigenvalues cannot be computed ({err}).') from None
    if not all_finite(ev):
        raise DimensionError('eigenvalues cannot be computed (overflow).')
    return np.asarray(ev, dtype=np.complex128)


def _finite_system(sys_: DiscreteSystem, what: str) -> DiscreteSystem:
    if not (all_finite(sys_.A) and all_finite(sys_.B)):
        raise DimensionError(f'{what}: the discrete system at dt = {sys_.dt:g} s overflows '
                             '(entries are not finite); the model is unusable at that step.')
    return sys_


def _finite_or_none(value: float) -> float | None:
    return value if np.isfinite(value) else None


def _names(kind: str, names: Sequence[str] | str | None, count: int, prefix: str) -> list[str]:
    if names is None:
        return [f'{prefix}{i + 1}' for i in range(count)]
    if isinstance(names, str):      # one unit for every channel; one name (not its letters)
        names = [names] * count if kind.endswith('units') else [names]
    names = [str(n) for n in names]
    if len(names) != count:
        raise DimensionError(f'{kind} must list {count} names; got {len(names)}.')
    return names


class LinearROM(ABC):
    """Common interface of every reduced-order model.

    Attributes
    ----------
    method : str
        ``'lopinf'``, ``'dmdc'`` or ``'era'``.
    dt : float
        Native sample time in seconds (training data step).
    y_ref : ndarray, shape (p,)
        Output reference (outputs at the reference configuration).
    input_names, output_names : list of str
    input_units, output_units : list of str
    metadata : dict
        Provenance and fit diagnostics, as JSON data (numpy values as Python ones, NaN and
        infinite numbers as ``None``).
    """

    method: ClassVar[str] = ''
    _matrix_names: ClassVar[tuple[str, ...]] = ()
    #: Arrays a file of this class may hold besides :attr:`_matrix_names` (loader hook).
    _optional_matrices: ClassVar[tuple[str, ...]] = ()
    #: Methods a file of this class may declare (empty: any short name).
    _file_methods: ClassVar[tuple[str, ...]] = ()

    def __init__(self, *, dt: float, y_ref: ArrayLike | None, n_inputs: int, n_outputs: int,
                 input_names: Sequence[str] | None = None,
                 output_names: Sequence[str] | None = None,
                 input_units: Sequence[str] | None = None,
                 output_units: Sequence[str] | None = None,
                 metadata: Mapping[str, Any] | None = None) -> None:
        self.dt = step_length(dt)
        self.y_ref = _arr('y_ref', np.zeros(n_outputs) if y_ref is None else y_ref,
                          (n_outputs,))
        self.input_names = _names('input_names', input_names, n_inputs, 'u')
        self.output_names = _names('output_names', output_names, n_outputs, 'y')
        self.input_units = _names('input_units', input_units or [''] * n_inputs, n_inputs, '')
        self.output_units = _names('output_units', output_units or [''] * n_outputs,
                                   n_outputs, '')
        self.metadata: dict[str, Any] = json_safe(dict(metadata or {}))  # NaN -> None
        self._native: DiscreteSystem | None = None
        self._trust: list[str] | None = None

    # -- sizes --------------------------------------------------------------------------
    @property
    @abstractmethod
    def r(self) -> int:
        """Reduced dimension (for LOpInf: size of ``q``; the state ``[q; q̇]`` has ``2r``)."""

    @property
    @abstractmethod
    def n_states(self) -> int:
        """Length of the state vector used by :meth:`step`."""

    @property
    def n_inputs(self) -> int:
        """Number of inputs ``m``."""
        return len(self.input_names)

    @property
    def n_outputs(self) -> int:
        """Number of outputs ``p``."""
        return len(self.output_names)

    # -- dynamics -----------------------------------------------------------------------
    @abstractmethod
    def discretize(self, dt: float | None = None) -> DiscreteSystem:
        """Return the discrete system for sample time ``dt`` (default :attr:`dt`).

        Inputs are held constant over each step (zero-order hold).
        """

    @property
    def system(self) -> DiscreteSystem:
        """The discrete system at the native :attr:`dt` (cached)."""
        if self._native is None:
            self._native = self.discretize(self.dt)
        return self._native

    def initial_state(self) -> Array:
        """The reference configuration (zero deviation, at rest)."""
        return np.zeros(self.n_states)

    def step(self, x: ArrayLike, u: ArrayLike, dt: float | None = None) -> Array:
        """Advance the state one sample: ``x_next = A x + B u``.

        Parameters
        ----------
        x : ndarray, shape (n_states,)
        u : ndarray, shape (m,)
            Absolute inputs (the models have no input offset).
        dt : float, optional
            Step length; default the native :attr:`dt`.

        ``x`` (n_states, k) with ``u`` (m, k) steps ``k`` states at once. A non-finite
        entry of ``x`` or ``u`` raises :class:`~soft_rom.errors.DimensionError`.
        """
        xs, us = _state_and_input(x, u, self.n_states, self.n_inputs)
        check_finite('x', xs, 'stepping')     # a NaN would turn every later state into NaN
        check_finite('u', us, 'stepping')
        sys_ = self.system if dt is None else self.discretize(dt)
        return sys_.A @ xs + sys_.B @ us

    def output(self, x: ArrayLike, u: ArrayLike | None = None) -> Array:
        """Absolute output ``y = C x + D u + y_ref``: (p,) for x (n,), (p, k) for x (n, k)."""
        sys_ = self.system
        if u is None:
            xs = _leading('x', x, self.n_states)
        else:
            xs, us = _state_and_input(x, u, self.n_states, self.n_inputs)
        y = sys_.C @ xs + (self.y_ref if xs.ndim == 1 else self.y_ref[:, None])
        if u is not None:
            y = y + sys_.D @ us
        return y

    def simulate(self, U: ArrayLike, x0: ArrayLike | None = None, *,
                 return_states: bool = False) -> Array | tuple[Array, Array]:
        """Simulate the model for inputs held over each native step.

        Parameters
        ----------
        U : ndarray, shape (m, k)
            Absolute inputs, one column per sample (finite: a NaN or Inf raises
            :class:`~soft_rom.errors.DimensionError` naming its index).
        x0 : ndarray, shape (n_states,), optional
            Initial state; default :meth:`initial_state`.
        return_states : bool
            Also return the states.

        Returns
        -------
        Y : ndarray, shape (p, k)
            Absolute outputs, ``Y[:, j] = C x_j + D u_j + y_ref``.
        X : ndarray, shape (n_states, k)
            States (only with ``return_states``).
        """
        U = as_signal('U', U, rows=self.n_inputs)
        check_finite('U', U, 'simulating')      # else every output from there on is NaN
        A, B, C, D, _ = self.system
        k = U.shape[1]
        x = self.initial_state() if x0 is None else _arr('x0', x0, (self.n_states,)).copy()
        X = run_states(A, B, x, U)[:, :k]
        Y = C @ X + D @ U + self.y_ref[:, None]
        return (Y, X) if return_states else Y

    def state_from_output(self, y: ArrayLike, u: ArrayLike | None = None) -> Array:
        """Least-squares state estimate from one measured absolute output.

        For the second-order model only ``q`` is observed; the velocity is set to zero.
        """
        dy = _arr('y', y, (self.n_outputs,)) - self.y_ref
        if u is not None:
            dy = dy - self.system.D @ _arr('u', u, (self.n_inputs,))
        x, *_ = np.linalg.lstsq(self.system.C, dy, rcond=None)
        return np.asarray(x, dtype=np.float64)

    # -- spectrum -----------------------------------------------------------------------
    def discrete_eigenvalues(self) -> NDArray[np.complex128]:
        """Eigenvalues of the native discrete state matrix ``A``."""
        return _eigvals(self.system.A)

    def stability_margin(self) -> float:
        """``1 - max |λ(A)|`` at the native ``dt``: positive means asymptotically stable.

        NaN when the eigenvalues cannot be computed (see :meth:`trust_issues`).
        """
        try:
            ev = self.discrete_eigenvalues()
        except DimensionError:
            return float('nan')
        return float(1.0 - np.max(np.abs(ev))) if ev.size else 1.0

    # -- trust --------------------------------------------------------------------------
    def trust_issues(self) -> list[str]:
        """Reasons not to trust this model's predictions; empty when there are none.

        Checked (relative tolerance :data:`TRUST_TOL`): the native discrete system is
        unstable (spectral radius of ``A`` above ``1 + tol``), the output offsets are absurd
        (``|y_ref| >`` :data:`ABSURD_OFFSET`), and for LOpInf models an eigenvalue of the
        continuous system with positive real part and a stiffness ``K`` or damping ``C``
        that is not symmetric positive semidefinite. A stable model whose steady state, for
        inputs held within the training range, moves an output by more than
        :data:`~soft_rom.gain.GAIN_FACTOR` times the largest training deviation has an
        absurd gain (:func:`soft_rom.gain.gain_issue`). Computed once, then cached.
        """
        if self._trust is None:
            self._trust = self._check_trust()
        return list(self._trust)

    @property
    def trusted(self) -> bool:
        """Whether :meth:`trust_issues` found nothing."""
        return not self.trust_issues()

    def _check_trust(self) -> list[str]:
        issues: list[str] = []
        margin = self.stability_margin()
        if not np.isfinite(margin):
            issues.append('the eigenvalues of its discrete system cannot be computed')
        elif margin < -TRUST_TOL:
            issues.append(f'unstable: spectral radius of the discrete A is {1 - margin:.6g} '
                          f'> 1 at dt = {self.dt:g} s')
        else:
            gain = gain_issue(self)
            if gain is not None:
                issues.append(gain)
        if self.y_ref.size:
            peak = float(np.max(np.abs(self.y_ref)))
            if peak > ABSURD_OFFSET:
                issues.append(f'absurd output offset: max |y_ref| = {peak:.3g}')
        return issues

    # -- files --------------------------------------------------------------------------
    def matrices(self) -> dict[str, Array]:
        """The model's defining matrices by name (read-only views)."""
        return {name: getattr(self, name) for name in self._matrix_names}

    def header(self) -> dict[str, Any]:
        """The JSON metadata written to a model file."""
        return {
            'format': FORMAT_NAME,
            'format_version': FORMAT_VERSION,
            'method': self.method,
            'class': type(self).__name__,
            'r': self.r,
            'n_states': self.n_states,
            'dt': self.dt,
            'input_names': self.input_names,
            'output_names': self.output_names,
            'input_units': self.input_units,
            'output_units': self.output_units,
            'stability_margin': _finite_or_none(self.stability_margin()),
            'metadata': self.metadata,
        }

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the model to ``path`` (``.npz``), atomically; returns the path written."""
        if self.n_states > MAX_STATES:
            raise ModelFileError(f'a model with {self.n_states} states cannot be saved: model '
                                 f'files hold at most {MAX_STATES} states.')
        path = Path(path)
        if path.suffix != '.npz':
            path = path.with_suffix(path.suffix + '.npz') if path.suffix else path.with_suffix(
                '.npz')
        arrays = dict(self.matrices())
        arrays['y_ref'] = self.y_ref
        meta = json.dumps(valid_text(self.header()), sort_keys=True,
                          allow_nan=False).encode('utf-8')
        arrays[_META_KEY] = np.frombuffer(meta, dtype=np.uint8)
        tmp = path.with_name(f'.{path.name}.tmp-{os.getpid()}')
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            with open(tmp, 'wb') as fh:
                # typed as Any: numpy 2's stubs give savez a keyword (allow_pickle) that
                # `**arrays` could fill, numpy 1's do not
                cast(Any, np.savez)(fh, **arrays)
            os.replace(tmp, path)
        finally:
            if tmp.exists():
                tmp.unlink()
        return path

    @classmethod
    def load(cls, path: str | os.PathLike[str], *, strict: bool = False) -> LinearROM:
        """Load a model file (see :func:`load_model`) and check it is of this class."""
        model = load_model(path, strict=strict)
        if not isinstance(model, cls):
            raise ModelFileError(
                f'{path}: holds a {type(model).__name__} ({model.method}), not a {cls.__name__}.')
        return model

    @classmethod
    def _from_file(cls, arrays: dict[str, Array], **common: Any) -> LinearROM:
        """Build a model from a file's arrays (loader hook; see :func:`register_model_class`).

        ``arrays`` holds :attr:`_matrix_names` (and any :attr:`_optional_matrices` present)
        as float64; ``common`` holds ``dt``, ``y_ref``, names, units, ``metadata`` and the
        declared ``method``.
        """
        common.pop('method', None)
        return cls(*(arrays[name] for name in cls._matrix_names), **common)

    def __repr__(self) -> str:
        return (f'{type(self).__name__}(method={self.method!r}, r={self.r}, m={self.n_inputs}, '
                f'p={self.n_outputs}, dt={self.dt:g})')


def load_model(path: str | os.PathLike[str], *, strict: bool = False) -> LinearROM:
    """Load a model file written by :meth:`LinearROM.save`, without executing any code.

    Every size is checked from the zip directory and the ``.npy`` headers before anything
    is read (:func:`soft_rom.models.archive.read_archive`: only the entries a model class
    needs, at most 32 MiB of arrays, float dtypes only, never pickle), the metadata JSON is
    parsed with size and depth limits, and every physical field is checked: ``dt`` finite in
    [1e-9, 1e4] s, ``1 <= n_states <=`` :data:`MAX_STATES` (r <= 256 for DMDc/ERA,
    r <= 128 for LOpInf), ``m, p >= 1``, shapes consistent with r, m and p, entries finite
    with magnitude at most 1e150, offsets ``|y_ref| <= 1e12``, and the discrete system at
    the native ``dt`` finite.

    Parameters
    ----------
    path : path
        The ``.npz`` model file.
    strict : bool
        Also refuse a model that loads but cannot be trusted
        (:meth:`LinearROM.trust_issues`).

    Raises
    ------
    FileNotFoundError
        No such file.
    ModelFileError
        Anything else wrong with the file, whatever its bytes (a ``ValueError``).
    """
    return cast(LinearROM, read_model(path, strict=strict))
