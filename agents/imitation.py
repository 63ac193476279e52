"""Behaviour cloning into an actor-critic agent (PPO, A3C, IMPALA): a warm start for RL.

:func:`clone` fits the agent's policy head to demonstrated discrete actions (cross-entropy)
and, given the demonstrations' discounted returns, its value head to them (squared error),
so that RL fine-tuning (``cosim train --init-from``, docs/agents.md "Warm start") starts
from a policy that acts like the demonstrator and a critic that already values its states.
The demonstrations are the caller's (studies/bc_warmstart.py drives the scripted autopilot).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F

from agents import observations
from agents.networks import obs_to_tensor

__all__ = ["clone", "cloned_network"]


def cloned_network(agent) -> torch.nn.Module:
    """The network :func:`clone` trains: the agent's one policy network, which must return
    ``(logits, value)`` (agents.networks.ActorCritic)."""
    from agents.registry import POLICY_NETWORKS

    names = POLICY_NETWORKS[agent.algo]
    if len(names) != 1 or not hasattr(agent.networks[names[0]], "policy_head"):
        raise ValueError(f"behaviour cloning needs an actor-critic agent (ppo, a3c, impala), "
                         f"got {agent.algo!r}")
    return agent.networks[names[0]]


def clone(agent, obs, actions: np.ndarray, returns: np.ndarray | None = None, *, epochs: int = 5,
          batch_size: int = 128, learning_rate: float = 3e-4, value_coef: float = 0.5,
          seed: int = 0, on_epoch: Callable[[int, dict], None] | None = None) -> dict:
    """Fit ``agent``'s policy to ``actions`` taken at ``obs`` (and its value to ``returns``).

    Args:
        agent: An actor-critic agent (:func:`cloned_network`), trained in place.
        obs: A batch of observations of the agent's space (an array, or a dict of arrays
            for a nav space), N first; or a list of such batches, N rows in all, taken as one
            (so demonstrations gathered in rounds are never copied into one array).
        actions: (N,) the demonstrated discrete actions.
        returns: (N,) discounted returns from each state, in the units the agent learns
            (already multiplied by its ``reward_scale``); None: the value head is not trained.
        epochs, batch_size, learning_rate: Adam over shuffled minibatches (its own optimizer:
            the agent's optimizer state is left as it was).
        value_coef: Weight of the value loss beside the cross-entropy.
        seed: Shuffling seed.
        on_epoch: Called after each epoch with (epoch, the epoch's mean metrics).

    Returns:
        The last epoch's mean ``loss``, ``cross_entropy``, ``value_loss`` and ``accuracy``
        (the fraction of minibatch actions the policy's argmax matched, before each step).
    """
    net = cloned_network(agent)
    chunks = list(obs) if isinstance(obs, list) else [obs]
    ends = np.cumsum([len(next(iter(c.values())) if isinstance(c, dict) else c) for c in chunks])
    actions = np.asarray(actions, dtype=np.int64)
    n = len(actions)
    if ends[-1] != n:
        raise ValueError(f"behaviour cloning got {ends[-1]} observations and {n} actions")
    if n == 0 or (returns is not None and len(returns) != n):
        raise ValueError(f"behaviour cloning needs as many returns as actions and at least one, "
                         f"got {n} actions and {None if returns is None else len(returns)} returns")
    optimizer = torch.optim.Adam(net.parameters(), lr=learning_rate, eps=1e-5)
    rng = np.random.default_rng(seed)
    net.train()
    metrics: dict = {}
    for epoch in range(epochs):
        sums = dict.fromkeys(("loss", "cross_entropy", "value_loss", "accuracy"), 0.0)
        order = rng.permutation(n)
        for start in range(0, n, batch_size):
            idx = np.sort(order[start:start + batch_size])
            logits, values = net(obs_to_tensor(_rows(chunks, ends, idx), agent.device))
            target = torch.as_tensor(actions[idx], device=agent.device)
            ce = F.cross_entropy(logits, target)
            loss = ce
            v_loss = torch.zeros(())
            if returns is not None:
                goal = torch.as_tensor(np.asarray(returns)[idx], dtype=torch.float32, device=agent.device)
                v_loss = 0.5 * ((values - goal) ** 2).mean()
                loss = loss + value_coef * v_loss
            optimizer.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), 0.5)
            optimizer.step()
            w = len(idx) / n
            sums["loss"] += w * loss.item()
            sums["cross_entropy"] += w * ce.item()
            sums["value_loss"] += w * v_loss.item()
            sums["accuracy"] += w * (logits.argmax(-1) == target).float().mean().item()
        metrics = sums
        if on_epoch is not None:
            on_epoch(epoch, metrics)
    net.eval()
    return metrics


def _rows(chunks: list, ends: np.ndarray, idx: np.ndarray):
    """Rows ``idx`` (sorted) of the batches ``chunks`` taken as one (their cumulative sizes ``ends``)."""
    if len(chunks) == 1:
        return observations.take(chunks[0], idx)
    which = np.searchsorted(ends, idx, side="right")
    starts = np.concatenate([[0], ends[:-1]])
    return observations.concatenate([observations.take(chunks[c], idx[which == c] - starts[c])
                                     for c in np.unique(which)])
