"""Return estimators against hand-worked cases (GAE, V-trace, n-step)."""

import numpy as np
import pytest

from agents.returns import gae, nstep_returns, vtrace


def test_gae_hand_computed_with_termination_and_truncation_inside_batch():
    # gamma = lam = 0.5; step 1 terminates (no bootstrap), step 2 is truncated
    # (bootstraps from next_values[2] but the trace stops there).
    # deltas = [1 + .5*2 - 1, 2 - 1, 3 + .5*4 - 1, 4 + .5*5 - 1, 5 + .5*6 - 1] = [1, 1, 4, 5.5, 7]
    advantages, returns = gae(
        rewards=[1, 2, 3, 4, 5],
        values=[1, 1, 1, 1, 1],
        next_values=[2, 3, 4, 5, 6],
        terminateds=[0, 1, 0, 0, 0],
        truncateds=[0, 0, 1, 0, 0],
        gamma=0.5,
        lam=0.5,
    )
    np.testing.assert_allclose(advantages, [1.25, 1.0, 4.0, 7.25, 7.0])
    np.testing.assert_allclose(returns, [2.25, 2.0, 5.0, 8.25, 8.0])


def test_gae_time_major_columns_are_independent():
    rewards = np.array([[1.0, 0.0], [1.0, 1.0]])
    adv, _ = gae(rewards, np.zeros((2, 2)), np.ones((2, 2)), np.array([[0, 1], [0, 0]]),
                 np.zeros((2, 2)), gamma=1.0, lam=1.0)
    # column 0: deltas [1 + 1, 1 + 1] -> A1 = 2, A0 = 2 + A1 = 4;
    # column 1 terminates at t0: delta0 = 0 and the trace is cut, A1 = 1 + 1 = 2.
    np.testing.assert_allclose(adv, [[4.0, 0.0], [2.0, 2.0]])


def test_gae_rejects_mismatched_shapes_with_the_name():
    with pytest.raises(ValueError, match="values"):
        gae([1, 2], [1], [1, 2], [0, 0], [0, 0], 0.9, 0.9)
    with pytest.raises(ValueError, match="gamma"):
        gae([1], [1], [1], [0], [0], 1.5, 0.9)


# Shared V-trace case: rhos = [2, 0.5, 1] -> clipped [1, 0.5, 1] (rho_bar = c_bar = 1).
LOG_MU = [0.0, 0.0, 0.0]
LOG_PI = [np.log(2.0), np.log(0.5), 0.0]
REWARDS = [1.0, 1.0, 1.0]
VALUES = [1.0, 2.0, 3.0]
NEXT_VALUES = [2.0, 3.0, 4.0]


def test_vtrace_hand_computed_without_episode_end():
    # deltas = [1*(1+.9*2-1), .5*(1+.9*3-2), 1*(1+.9*4-3)] = [1.8, .85, 1.6]
    # vs - V: [1.8 + .9*1*1.57, .85 + .9*.5*1.6, 1.6] = [3.213, 1.57, 1.6]
    vs, pg = vtrace(LOG_MU, LOG_PI, REWARDS, VALUES, NEXT_VALUES, [0.9, 0.9, 0.9])
    np.testing.assert_allclose(vs, [4.213, 3.57, 4.6], rtol=1e-6)
    # pg = rho * (r + .9 * v_{s+1} - V): [1*(1+.9*3.57-1), .5*(1+.9*4.6-2), 1*(1+.9*4-3)]
    np.testing.assert_allclose(pg, [3.213, 1.57, 1.6], rtol=1e-6)


def test_vtrace_hand_computed_with_termination():
    vs, pg = vtrace(LOG_MU, LOG_PI, REWARDS, VALUES, NEXT_VALUES, [0.9, 0.0, 0.9])
    # step 1 terminates: delta_1 = .5*(1 - 2) = -.5 and the trace is cut there.
    np.testing.assert_allclose(vs, [2.35, 1.5, 4.6], rtol=1e-6)
    np.testing.assert_allclose(pg, [1.35, -0.5, 1.6], rtol=1e-6)


def test_vtrace_truncation_cuts_trace_but_bootstraps():
    vs, pg = vtrace(LOG_MU, LOG_PI, REWARDS, VALUES, NEXT_VALUES, [0.9, 0.9, 0.9],
                    episode_ends=[0, 1, 0])
    np.testing.assert_allclose(vs, [3.565, 2.85, 4.6], rtol=1e-6)
    np.testing.assert_allclose(pg, [2.565, 0.85, 1.6], rtol=1e-6)


def test_vtrace_on_policy_equals_gae_lambda_one():
    rng = np.random.default_rng(0)
    rewards, values = rng.normal(size=6), rng.normal(size=6)
    next_values = np.append(values[1:], rng.normal())
    log_p = rng.normal(size=6)
    vs, pg = vtrace(log_p, log_p, rewards, values, next_values, np.full(6, 0.9))
    adv, returns = gae(rewards, values, next_values, np.zeros(6), np.zeros(6), 0.9, 1.0)
    np.testing.assert_allclose(vs, returns, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(pg, adv, rtol=1e-5, atol=1e-5)


def test_nstep_returns_hand_computed():
    # gamma .5, n 2, step 2 terminates.
    out = nstep_returns([1, 1, 1, 1], [10, 10, 10, 10], [0, 0, 1, 0], gamma=0.5, n=2)
    np.testing.assert_allclose(out, [1 + 0.5 + 0.25 * 10, 1 + 0.5, 1.0, 1 + 0.5 * 10])


def test_nstep_truncation_stops_window_and_bootstraps():
    out = nstep_returns([1, 1, 1], [10, 20, 30], [0, 0, 0], gamma=0.5, n=3, truncateds=[1, 0, 0])
    np.testing.assert_allclose(out, [1 + 0.5 * 10, 1 + 0.5 + 0.25 * 30, 1 + 0.5 * 30])


def test_nstep_one_step_is_td_target():
    out = nstep_returns([1.0, 2.0], [3.0, 4.0], [0, 1], gamma=0.9, n=1)
    np.testing.assert_allclose(out, [1 + 0.9 * 3, 2.0])
