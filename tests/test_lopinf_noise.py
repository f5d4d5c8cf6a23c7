"""LOpInf on noisy coordinates: Savitzky-Golay derivatives with automatic regularization.

A 30-DOF damped spring chain reduced to r = 4 (POD of the training states): the noise-free
fit has a known floor (truncation, about 3 % deviation error on an unseen episode). White
noise of 2 mm on every nodal coordinate and output (0.7 % of the RMS deviation, but enough
to make 8th-order finite-difference accelerations useless: their fit is several times
worse) must leave the Savitzky-Golay + ``regularization='auto'`` fit within 20 % of the
noise-free one, for several noise draws. Errors against the clean outputs of a held-out
episode, simulated from rest.
"""

from __future__ import annotations

from _systems import spring_chain_episodes
import numpy as np
import pytest

from soft_rom.data import Episode
from soft_rom.ddt import FiniteDifference, SavitzkyGolay
from soft_rom.evaluation import predict
from soft_rom.learners.lopinf import LOpInf
from soft_rom.metrics import relative_deviation_error

N_DOF, R, SIGMA = 30, 4, 2e-3


@pytest.fixture(scope='module')
def chain() -> tuple[list[Episode], Episode, np.ndarray, np.ndarray]:
    eps = spring_chain_episodes(n_dof=N_DOF, m=2, p=6, k=1500, dt=0.004, seed=3,
                                stiffness=400.0, drive_nodes=(10, 20), input_gain=50.0,
                                amplitude=1.0, hold=40, q_span=1.0, n_episodes=3)
    q_ref = np.linspace(0.0, 1.0, N_DOF)
    return eps[:2], eps[2], q_ref, eps[0].Y[:, 0].copy()


def _test_error(chain: tuple[list[Episode], Episode, np.ndarray, np.ndarray],
                train: list[Episode], **kw: object) -> float:
    _train, test, q_ref, y_ref = chain
    model = LOpInf(r=R, **kw).fit(train, q_ref=q_ref, y_ref=y_ref).model_
    Yh = predict(model, test)
    assert np.all(np.isfinite(Yh))
    return relative_deviation_error(test.Y, Yh, y_ref)


def _noisy(train: list[Episode], seed: int) -> list[Episode]:
    rng = np.random.default_rng(seed)
    return [Episode(t=e.t, U=e.U, Y=e.Y + SIGMA * rng.standard_normal(e.Y.shape),
                    Q=e.Q + SIGMA * rng.standard_normal(e.Q.shape), name=e.name)
            for e in train]


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_savgol_auto_regularization_within_20_percent_of_noise_free(chain, seed) -> None:
    train = chain[0]
    clean = _test_error(chain, train, ddt=SavitzkyGolay(), regularization=None)
    assert 0.01 < clean < 0.06                     # the truncation floor of r = 4
    noisy = _noisy(train, seed)
    auto = _test_error(chain, noisy, ddt=SavitzkyGolay(), regularization='auto')
    assert auto <= 1.2 * clean
    # the noise is not negligible: finite-difference accelerations are swamped by it
    fd = _test_error(chain, noisy, ddt=FiniteDifference(8), regularization='auto')
    assert fd > 3 * clean
