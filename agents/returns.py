"""Return and advantage estimators as pure numpy functions.

All arrays are time-major: shape ``(T,)`` for one stream or ``(T, N)`` for N
parallel streams (agents or envs). Index ``t`` describes the transition
``(s_t, a_t, r_t, s_{t+1})``, and ``next_values[t]`` is the value of the
observation that *followed* step ``t`` (the final observation of an episode
when it ended at ``t``, not the first observation after a reset). This is what
lets truncation bootstrap correctly while termination does not (see Pardo et
al. 2018, "Time Limits in Reinforcement Learning").

Functions:
    gae: Generalised advantage estimation (Schulman et al. 2016).
    vtrace: V-trace targets and policy-gradient advantages (Espeholt et al. 2018).
    nstep_returns: n-step bootstrapped returns.
"""

from __future__ import annotations

import numpy as np

__all__ = ["gae", "nstep_returns", "vtrace"]


def _as_float(name: str, array) -> np.ndarray:
    out = np.asarray(array, dtype=np.float64)
    if out.ndim not in (1, 2):
        raise ValueError(f"{name} must be time-major with shape (T,) or (T, N), got shape {out.shape}")
    if out.shape[0] == 0:
        raise ValueError(f"{name} is empty: need at least one time step")
    return out


def _check_shapes(reference: str, shape: tuple[int, ...], **arrays: np.ndarray) -> None:
    for name, array in arrays.items():
        if array.shape != shape:
            raise ValueError(
                f"{name} has shape {array.shape} but {reference} has shape {shape}; "
                "all inputs must be time-major arrays of the same shape"
            )


def _as_flags(name: str, array, shape: tuple[int, ...]) -> np.ndarray:
    out = np.asarray(array)
    _check_shapes("rewards", shape, **{name: out})
    return out.astype(bool)


def gae(
    rewards,
    values,
    next_values,
    terminateds,
    truncateds,
    gamma: float,
    lam: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Generalised advantage estimation over a time-major batch.

    ``delta_t = r_t + gamma * (1 - terminated_t) * next_values_t - values_t`` and
    ``A_t = delta_t + gamma * lam * (1 - done_t) * A_{t+1}`` with
    ``done_t = terminated_t or truncated_t``: a truncated step still bootstraps
    from ``next_values_t`` but the advantage does not leak into the next episode.
    The last step of the batch bootstraps from ``next_values[-1]``.

    Args:
        rewards: ``(T,)`` or ``(T, N)`` rewards.
        values: ``V(s_t)``, same shape.
        next_values: ``V(s_{t+1})`` of the observation that followed step t.
        terminateds: True where the episode terminated at step t (no bootstrap).
        truncateds: True where the episode was cut at step t (bootstrap).
        gamma: Discount factor in [0, 1].
        lam: GAE lambda in [0, 1].

    Returns:
        ``(advantages, returns)`` as float32 arrays, ``returns = advantages + values``.

    Raises:
        ValueError: On mismatched shapes or out-of-range gamma/lam.
    """
    if not (0.0 <= gamma <= 1.0 and 0.0 <= lam <= 1.0):
        raise ValueError(f"gae needs gamma and lam in [0, 1], got gamma={gamma}, lam={lam}")
    rewards = _as_float("rewards", rewards)
    values, next_values = np.asarray(values, np.float64), np.asarray(next_values, np.float64)
    _check_shapes("rewards", rewards.shape, values=values, next_values=next_values)
    terminated = _as_flags("terminateds", terminateds, rewards.shape)
    done = terminated | _as_flags("truncateds", truncateds, rewards.shape)

    deltas = rewards + gamma * (~terminated) * next_values - values
    advantages = np.zeros_like(rewards)
    last = np.zeros_like(rewards[0])
    for t in reversed(range(rewards.shape[0])):
        last = deltas[t] + gamma * lam * (~done[t]) * last
        advantages[t] = last
    return advantages.astype(np.float32), (advantages + values).astype(np.float32)


def vtrace(
    behaviour_log_probs,
    target_log_probs,
    rewards,
    values,
    next_values,
    discounts,
    rho_bar: float = 1.0,
    c_bar: float = 1.0,
    episode_ends=None,
) -> tuple[np.ndarray, np.ndarray]:
    """V-trace value targets and policy-gradient advantages (Espeholt et al. 2018, eq. 1).

    With ``rho_t = min(rho_bar, pi/mu)`` and ``c_t = min(c_bar, pi/mu)``:
    ``delta_t = rho_t (r_t + discount_t * V(x_{t+1}) - V(x_t))`` and
    ``v_s - V(x_s) = delta_s + discount_s * c_s * (v_{s+1} - V(x_{s+1}))``.
    The policy-gradient advantage is
    ``rho_s (r_s + discount_s * v_{s+1} - V(x_s))``.

    Args:
        behaviour_log_probs: ``log mu(a_t|x_t)`` of the actor that acted.
        target_log_probs: ``log pi(a_t|x_t)`` of the learner's current policy.
        rewards: ``r_t``.
        values: ``V(x_t)``.
        next_values: ``V(x_{t+1})``, the value of the observation that followed t.
        discounts: ``gamma * (1 - terminated_t)`` per step.
        rho_bar: Truncation level of the importance weights in ``delta`` and the
            policy-gradient advantage.
        c_bar: Truncation level of the trace-cutting coefficients ``c``.
        episode_ends: Optional flags, True where an episode ended at t (terminated
            *or* truncated). They stop the recursion from reaching into the next
            episode while ``next_values`` still bootstraps a truncation. Default:
            ends where ``discounts == 0`` (termination only).

    Returns:
        ``(vs, pg_advantages)`` as float32 arrays of the input shape.

    Raises:
        ValueError: On mismatched shapes or negative clipping thresholds.
    """
    if rho_bar <= 0 or c_bar <= 0:
        raise ValueError(f"vtrace needs rho_bar > 0 and c_bar > 0, got {rho_bar}, {c_bar}")
    rewards = _as_float("rewards", rewards)
    arrays = {
        "behaviour_log_probs": np.asarray(behaviour_log_probs, np.float64),
        "target_log_probs": np.asarray(target_log_probs, np.float64),
        "values": np.asarray(values, np.float64),
        "next_values": np.asarray(next_values, np.float64),
        "discounts": np.asarray(discounts, np.float64),
    }
    _check_shapes("rewards", rewards.shape, **arrays)
    values, next_values, discounts = arrays["values"], arrays["next_values"], arrays["discounts"]
    if episode_ends is None:
        ends = discounts == 0.0
    else:
        ends = _as_flags("episode_ends", episode_ends, rewards.shape)

    rhos = np.exp(arrays["target_log_probs"] - arrays["behaviour_log_probs"])
    clipped_rhos = np.minimum(rho_bar, rhos)
    cs = np.minimum(c_bar, rhos)
    deltas = clipped_rhos * (rewards + discounts * next_values - values)

    vs_minus_values = np.zeros_like(rewards)
    acc = np.zeros_like(rewards[0])
    for t in reversed(range(rewards.shape[0])):
        acc = deltas[t] + discounts[t] * cs[t] * (~ends[t]) * acc
        vs_minus_values[t] = acc
    vs = values + vs_minus_values

    # v_{s+1}: the corrected next target inside an episode, the plain bootstrap value
    # at an episode end or at the end of the batch.
    next_corrections = np.zeros_like(rewards)
    next_corrections[:-1] = vs_minus_values[1:]
    vs_next = next_values + (~ends) * next_corrections
    pg_advantages = clipped_rhos * (rewards + discounts * vs_next - values)
    return vs.astype(np.float32), pg_advantages.astype(np.float32)


def nstep_returns(
    rewards, next_values, dones, gamma: float, n: int, truncateds=None
) -> np.ndarray:
    """n-step bootstrapped returns.

    ``G_t = sum_{k<m} gamma^k r_{t+k} + gamma^m * next_values[t+m-1]`` where the
    window of ``m <= n`` steps stops at the first episode end or the batch end;
    the bootstrap term is dropped when the window ends in a termination.

    Args:
        rewards: ``(T,)`` or ``(T, N)`` rewards.
        next_values: Value of the observation that followed step t.
        dones: True where the episode *terminated* at step t (no bootstrap).
        gamma: Discount factor in [0, 1].
        n: Number of steps, >= 1 (1 gives the one-step TD target).
        truncateds: Optional flags where the episode was cut at t: the window stops
            there but still bootstraps from ``next_values``.

    Returns:
        float32 returns of the input shape.

    Raises:
        ValueError: On mismatched shapes, n < 1 or gamma outside [0, 1].
    """
    if n < 1:
        raise ValueError(f"nstep_returns needs n >= 1, got {n}")
    if not 0.0 <= gamma <= 1.0:
        raise ValueError(f"nstep_returns needs gamma in [0, 1], got {gamma}")
    rewards = _as_float("rewards", rewards)
    next_values = np.asarray(next_values, np.float64)
    _check_shapes("rewards", rewards.shape, next_values=next_values)
    terminated = _as_flags("dones", dones, rewards.shape)
    truncated = (
        np.zeros_like(terminated) if truncateds is None
        else _as_flags("truncateds", truncateds, rewards.shape)
    )
    horizon = rewards.shape[0]
    returns = np.zeros_like(rewards)
    for t in range(horizon):
        total = np.zeros_like(rewards[0])
        discount = np.ones_like(rewards[0])
        open_ = np.ones_like(rewards[0], dtype=bool)  # still inside the episode of step t
        bootstrap = np.zeros_like(rewards[0])
        for k in range(min(n, horizon - t)):
            step = t + k
            total += open_ * discount * rewards[step]
            discount = np.where(open_, discount * gamma, discount)
            window_ends = terminated[step] | truncated[step] | (k == n - 1) | (step == horizon - 1)
            closing = open_ & window_ends
            bootstrap += closing * (~terminated[step]) * discount * next_values[step]
            open_ = open_ & ~window_ends
        returns[t] = total + bootstrap
    return returns.astype(np.float32)
