"""Tests of soft_rom.ddt: order of accuracy, trimmed edges, episodes kept apart."""

from __future__ import annotations

import numpy as np
import pytest

from soft_rom.ddt import as_estimator, DerivativeEstimator, FiniteDifference
from soft_rom.errors import ConfigError, DimensionError


def _errors(order: int, dt: float) -> tuple[float, float, float]:
    t = np.arange(0.0, 4.0 + dt / 2, dt)
    w = 1.3
    Q = np.vstack([np.sin(w * t), np.cos(0.7 * t) * np.exp(0.2 * t)])
    fd = FiniteDifference(order)
    Qm, d1, d2 = fd.derivatives(Q, dt)
    tm = fd.trim(t)[0]
    e_d1 = np.vstack([w * np.cos(w * tm),
                      (-0.7 * np.sin(0.7 * tm) + 0.2 * np.cos(0.7 * tm)) * np.exp(0.2 * tm)])
    e_d2 = np.vstack([-w ** 2 * np.sin(w * tm),
                      (-0.49 * np.cos(0.7 * tm) - 0.28 * np.sin(0.7 * tm)
                       + 0.04 * np.cos(0.7 * tm)) * np.exp(0.2 * tm)])
    assert np.array_equal(Qm, fd.trim(Q))
    return (float(np.max(np.abs(d1 - e_d1))), float(np.max(np.abs(d2 - e_d2))),
            float(np.max(np.abs(Qm[0] - np.sin(w * tm)))))


@pytest.mark.parametrize('order', [2, 4, 6, 8])
def test_nominal_order_of_accuracy(order):
    # Step sizes chosen so that truncation error dominates rounding (~1e-16/dt^2).
    dt = {2: 0.02, 4: 0.05, 6: 0.1, 8: 0.2}[order]
    e1a, e2a, e0 = _errors(order, dt)
    e1b, e2b, _ = _errors(order, dt / 2)
    rate1, rate2 = np.log2(e1a / e1b), np.log2(e2a / e2b)
    assert e0 == 0.0
    assert abs(rate1 - order) < 0.25, rate1
    assert abs(rate2 - order) < 0.25, rate2


@pytest.mark.parametrize('order', [2, 4, 6, 8])
def test_exact_on_polynomials_and_shapes(order):
    # A central difference of order p is exact on polynomials of degree <= p.
    dt, k = 0.1, 40
    t = np.arange(k) * dt
    c = np.arange(1, order + 2) / 10.0
    q = np.polynomial.Polynomial(c)
    fd = FiniteDifference(order)
    Qm, d1, d2 = fd.derivatives(q(t), dt)
    h = order // 2
    assert fd.half_width == h
    assert Qm.shape == d1.shape == d2.shape == (1, k - order)
    tm = t[h:k - h]
    np.testing.assert_allclose(d1[0], q.deriv(1)(tm), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(d2[0], q.deriv(2)(tm), rtol=1e-8, atol=1e-8)


def test_episodes_never_straddle():
    dt = 0.01
    t = np.arange(100) * dt
    a = np.vstack([t ** 2, np.sin(t)])
    b = np.vstack([5.0 - 3.0 * t, 10.0 + np.cos(3 * t)])   # jump at the junction
    u_a, u_b = np.ones((1, 100)), 2 * np.ones((1, 100))
    fd = FiniteDifference(4)
    Q, Qd, Qdd, (U,) = fd.episodes([a, b], dt, [[u_a, u_b]])
    for i, part in enumerate((a, b)):
        ref = fd.derivatives(part, dt)
        sl = slice(i * 96, (i + 1) * 96)
        for got, want in zip((Q, Qd, Qdd), ref):
            np.testing.assert_array_equal(got[:, sl], want)
    np.testing.assert_array_equal(U, np.hstack([np.ones((1, 96)), 2 * np.ones((1, 96))]))
    # First derivative of t^2 is 2t exactly, even next to the junction.
    np.testing.assert_allclose(Qd[0, :96], 2 * t[2:98], atol=1e-10)


def test_errors_and_protocol():
    with pytest.raises(ConfigError):
        FiniteDifference(3)
    with pytest.raises(DimensionError):
        FiniteDifference(8).derivatives(np.zeros((2, 8)), 0.1)
    with pytest.raises(DimensionError):
        FiniteDifference(2).derivatives(np.zeros((2, 8)), -0.1)
    assert isinstance(FiniteDifference(), DerivativeEstimator)
    assert as_estimator(6).order == 6
    fd = FiniteDifference(2)
    assert as_estimator(fd) is fd
    with pytest.raises(ConfigError):
        as_estimator('eight')


def test_savgol_exact_on_polynomials_and_trims_like_fd():
    from soft_rom.ddt import SavitzkyGolay
    dt = 0.01
    t = dt * np.arange(200)
    Q = np.stack([1 + 2 * t - 3 * t ** 2 + 0.5 * t ** 3, t ** 4])
    sg = SavitzkyGolay(21, 4)
    Qm, d1, d2 = sg.derivatives(Q, dt)
    tm = t[10:-10]
    assert Qm.shape == (2, 180) and sg.trim(Q).shape == (2, 180)
    np.testing.assert_allclose(Qm, Q[:, 10:-10], rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(sg.trim(Q), Qm, rtol=0, atol=0)       # one filter for all
    np.testing.assert_allclose(d1[0], 2 - 6 * tm + 1.5 * tm ** 2, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(d2[0], -6 + 3 * tm, rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(d2[1], 12 * tm ** 2, rtol=1e-8, atol=1e-8)


def test_savgol_suppresses_noise_that_fd8_amplifies():
    from soft_rom.ddt import FiniteDifference, SavitzkyGolay
    rng = np.random.default_rng(0)
    dt = 1 / 120
    t = dt * np.arange(1200)
    q = 0.02 * np.sin(2 * np.pi * 0.7 * t)                     # 2 cm at 0.7 Hz
    true_dd = -(2 * np.pi * 0.7) ** 2 * q
    noisy = (q + 0.0005 * rng.standard_normal(t.size))[None]    # 0.5 mm mocap noise
    errs = {}
    for est in (FiniteDifference(8), SavitzkyGolay(31, 3)):
        _, _, d2 = est.derivatives(noisy, dt)
        ref = est.trim(true_dd[None])     # SG: the filtered truth (the fit's target)
        errs[repr(est)] = np.linalg.norm(d2 - ref) / np.linalg.norm(ref)
    assert errs['FiniteDifference(order=8)'] > 10      # noise dominates completely
    assert errs['SavitzkyGolay(window=31, polyorder=3)'] < 0.15


def test_parse_estimator_names():
    from soft_rom.ddt import FiniteDifference, parse_estimator, SavitzkyGolay
    from soft_rom.errors import ConfigError
    assert parse_estimator('fd4').order == 4 and isinstance(parse_estimator('FD8'),
                                                            FiniteDifference)
    sg = parse_estimator('savgol:31:3')
    assert isinstance(sg, SavitzkyGolay) and (sg.window, sg.polyorder) == (31, 3)
    for bad in ('fd3', 'savgol:20', 'savgol:x', 'savgol:5:4', 'spline'):
        with pytest.raises(ConfigError):
            parse_estimator(bad)
