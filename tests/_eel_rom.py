"""A small exact ROM of the embedded eel: the FOM linearized at rest, on its lowest modes.

Fast to build (one sparse eigen-solve, ~1 s) and with the eel's output layout, so that the
closed-loop tests run the real FOM as the plant without fitting a model first.
"""

from __future__ import annotations

import functools

import numpy as np
import scipy.sparse.linalg as spla

from soft_rom.models import SecondOrderModel
from soft_rom.sim import EelModel


@functools.lru_cache(maxsize=2)
def eel() -> EelModel:
    return EelModel()


@functools.lru_cache(maxsize=4)
def modal_rom(r: int = 8) -> SecondOrderModel:
    """Galerkin ROM of the linearized eel on its ``r`` lowest M-orthonormal modes."""
    model = eel()
    lin = model.linearization()
    free = lin.free
    K = lin.K[free][:, free].tocsc()
    M = lin.M[free][:, free].tocsc()
    w2, phi = spla.eigsh(K, k=r, M=M, sigma=0.0, which='LM')
    order = np.argsort(w2)
    w2, phi = w2[order], phi[:, order]
    V = np.zeros((model.n_dof, r))
    V[free] = phi
    Kr = np.diag(w2)
    Cr = V.T @ (lin.C @ V)
    Br = V.T @ lin.B
    Er = lin.E @ V
    names = [f'{c}{i}' for c in 'xz' for i in range(1, 21)]
    return SecondOrderModel(Kr, 0.5 * (Cr + Cr.T), Br, Er, dt=1e-3, y_ref=lin.y_ref,
                            output_names=names, input_names=[f'chamber_{i}' for i in range(1, 7)],
                            input_units=['Pa'] * 6, output_units=['m'] * 40,
                            metadata={'envelope': {'u_min': [-50e3] * 6, 'u_max': [50e3] * 6,
                                                   'y_dev_max': 0.03, 'samples': 0}})
