"""Known systems shared by the tests: a damped spring chain, a second-order linear FOM."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.linalg as sla

from soft_rom.data import Episode


def spring_chain_episodes(*, n_dof: int, m: int, p: int, k: int, dt: float, seed: int,
                          stiffness: float, drive_nodes: Sequence[int], input_gain: float,
                          amplitude: float, hold: int, q_span: float,
                          output_noise: float = 0.0, n_episodes: int = 2) -> list[Episode]:
    """Episodes of a damped spring chain ``q'' + C q' + K q = B u`` with full states.

    The chain is integrated exactly for inputs held over each step; inputs are random levels
    in ``[0, amplitude]`` held for ``hold`` samples, one chamber per ``drive_nodes`` entry
    (force ``input_gain * u``); outputs are ``E q`` (plus optional white noise) with a random
    ``E``; states are centred on ``q_ref = linspace(0, q_span, n_dof)``.
    """
    rng = np.random.default_rng(seed)
    K = stiffness * (2 * np.eye(n_dof) - np.eye(n_dof, k=1) - np.eye(n_dof, k=-1))
    C = 0.02 * K + 0.5 * np.eye(n_dof)
    Bf = np.zeros((n_dof, m))
    for j, node in enumerate(drive_nodes):
        Bf[node, j] = input_gain
    Ac = np.block([[np.zeros((n_dof, n_dof)), np.eye(n_dof)], [-K, -C]])
    Bc = np.vstack([np.zeros((n_dof, m)), Bf])
    M = np.zeros((2 * n_dof + m,) * 2)
    M[:2 * n_dof, :2 * n_dof], M[:2 * n_dof, 2 * n_dof:] = Ac * dt, Bc * dt
    F = sla.expm(M)
    Ad, Bd = F[:2 * n_dof, :2 * n_dof], F[:2 * n_dof, 2 * n_dof:]
    E = rng.standard_normal((p, n_dof))
    q_ref = np.linspace(0.0, q_span, n_dof)
    eps = []
    for i in range(n_episodes):
        U = np.repeat(rng.uniform(0, amplitude, (m, k // hold + 1)), hold, axis=1)[:, :k]
        x, X = np.zeros(2 * n_dof), np.empty((2 * n_dof, k))
        for j in range(k):
            X[:, j] = x
            x = Ad @ x + Bd @ U[:, j]
        Q = X[:n_dof] + q_ref[:, None]
        Y = E @ Q
        if output_noise:
            Y = Y + output_noise * rng.standard_normal((p, k))
        eps.append(Episode(t=np.arange(k) * dt, U=U, Y=Y, Q=Q, name=f'ep{i + 1}'))
    return eps
