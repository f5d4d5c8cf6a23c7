"""Test data of the soft_rom.scale tests: low-rank snapshots, a lifted LTI system, a dense POD."""

from __future__ import annotations

import numpy as np

from soft_rom.data import Episode

N, RT, M, P, DT = 600, 8, 3, 5, 0.01


def lowrank(seed: int = 1, n: int = 800, ks=(200, 150, 170), rank: int = 25,
             noise: float = 1e-7):
    """Snapshots with a decaying spectrum (1 .. 1e-4) plus white noise."""
    rng = np.random.default_rng(seed)
    modes = np.linalg.qr(rng.standard_normal((n, rank)))[0]
    amp = np.logspace(0, -4, rank)
    q_ref = rng.standard_normal(n)
    arrays = [q_ref[:, None] + modes @ (amp[:, None] * rng.standard_normal((rank, k)))
              + noise * rng.standard_normal((n, k)) for k in ks]
    return arrays, q_ref


def system_episodes(seed: int = 0, ks=(200, 160), noise: float = 0.0):
    """A stable discrete LTI system lifted to N states by a fixed random map (exact rank RT)."""
    rng = np.random.default_rng(seed)
    A = np.linalg.qr(rng.standard_normal((RT, RT)))[0] * 0.97
    B = rng.standard_normal((RT, M))
    Phi = rng.standard_normal((N, RT))
    C = rng.standard_normal((P, RT))
    q_ref, y_ref = rng.standard_normal(N), rng.standard_normal(P)
    eps = []
    for e, k in enumerate(ks):
        U = rng.standard_normal((M, k))
        X = np.zeros((RT, k))
        for j in range(k - 1):
            X[:, j + 1] = A @ X[:, j] + B @ U[:, j]
        Q = Phi @ X + q_ref[:, None] + noise * rng.standard_normal((N, k))
        eps.append(Episode(t=np.arange(k) * DT, U=U, Y=C @ X + y_ref[:, None], Q=Q,
                           name=f'ep{e + 1}'))
    return eps, q_ref, y_ref


def training_set(tmp_path, eps, q_ref, y_ref, chunks=(512, 32)):
    from soft_rom.dataset import TrainingSet
    return TrainingSet.from_episodes(tmp_path / 'ts.zarr', eps, q_ref=q_ref, y_ref=y_ref,
                                     q_chunks=chunks)


def basis_error(V, U):
    """Largest entry difference after the sign convention (both fixed the same way)."""
    return float(np.max(np.abs(V - U)))


def dense_reference(arrays, q_ref):
    """Dense SVD of the centred snapshots: ``(U, s)``, each mode's largest entry positive.

    The sign convention is that of :class:`soft_rom.basis.POD` and
    :class:`soft_rom.scale.pod.StreamingPOD`, written out again here so the tests check it.
    """
    X = np.concatenate([np.asarray(a, dtype=np.float64) for a in arrays], axis=1)
    X = X - np.asarray(q_ref, dtype=np.float64).reshape(-1, 1)
    U, s, _ = np.linalg.svd(X, full_matrices=False)
    signs = np.sign(U[np.argmax(np.abs(U), axis=0), np.arange(U.shape[1])])
    signs[signs == 0] = 1.0
    return U * signs, s


def lowrank_episodes(arrays):
    """Episodes carrying the snapshot arrays (zero inputs and outputs)."""
    return [Episode(t=np.arange(a.shape[1]) * DT, U=np.zeros((1, a.shape[1])),
                    Y=np.zeros((1, a.shape[1])), Q=a, name=f'e{i}') for i, a in enumerate(arrays)]
