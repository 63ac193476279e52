"""Parameter sharing: one agent's networks drive (and learn from) every AC.

The common multi-agent baseline (Gupta et al. 2017, "parameter sharing"): instead of one
network per AC, as the paper trained them, the N ACs of a run act with ONE network, and every
AC's transitions feed its ONE learner. Each AC then learns from N times the transitions of its
own car at the same compute: the learner does the same work per transition as N independent
ones would (PPO updates when ``rollout_steps`` transitions are in, from whichever ACs; DQN, DDPG
and TD3 take ``gradient_steps`` every ``train_freq`` transitions), so N times as many updates
land on the one network. The paper's setting (independent networks) stays the default;
``cosim train --share-params`` turns this on (docs/agents.md, "Parameter sharing").

:func:`share` wraps one agent (the *core*) into one :class:`SharedSlot` per AC. A slot is an
:class:`~agents.base.Agent` for the loops (agents/loop.py): it maps its (environment) columns to
columns of its own, ``column * n_slots + slot``, so the core's per-column state (PPO's pending
log-probabilities and GAE sequences, the replay rings of DQN, DDPG and TD3) keeps every AC's
sequence of transitions apart, and it runs the core's ``update()`` under one lock (the vector loop
may call the slots' updates on several threads; the core learns what is due once, the other
calls find nothing due). Saving a slot saves the core, so every AC's checkpoint holds the one
network and the test drives each slot with it, as it would any checkpoint.

Only algorithms that train in the sync loop (PPO, DQN, DDPG, TD3) can share: A3C and IMPALA
build their own learners (agents/registry.py).
"""

from __future__ import annotations

import threading
from collections.abc import Sequence

import numpy as np

from agents.base import Agent

__all__ = ["SharedSlot", "share", "shared_core"]


class SharedSlot(Agent):
    """AC ``slot`` of ``n_slots`` acting and learning with a shared core agent.

    Not built by the constructor of :class:`Agent` (it has no networks of its own): use
    :func:`share`. Attributes not defined here (``config``, spaces, ``networks``, ``optimizers``,
    ``device``, ``seed``, ``steps`` ...) are the core's.
    """

    def __init__(self, core: Agent, slot: int, n_slots: int, lock: threading.Lock):  # noqa: D107
        # deliberately not Agent.__init__: the core owns every network, optimizer and generator
        self.__dict__.update(core=core, slot=int(slot), n_slots=int(n_slots), lock=lock)

    def __getattr__(self, name):
        try:
            core = self.__dict__["core"]
        except KeyError:  # before __init__ (copy, pickle): no core to ask
            raise AttributeError(name) from None
        return getattr(core, name)

    # the class attributes the loops and checkpoints read, as the core's class has them
    @property
    def algo(self) -> str:  # type: ignore[override]
        return self.core.algo

    @property
    def config_class(self):  # type: ignore[override]
        return self.core.config_class

    @property
    def policy_only(self) -> bool:  # type: ignore[override]
        return self.core.policy_only

    @property
    def optimizer_learning_rates(self):  # type: ignore[override]
        return self.core.optimizer_learning_rates

    @property
    def progress_remaining(self) -> float:  # type: ignore[override]
        """The core's: what the loop sets before ``update()`` reaches the one learner."""
        return self.core.progress_remaining

    @progress_remaining.setter
    def progress_remaining(self, value: float) -> None:
        self.core.progress_remaining = value

    @classmethod
    def check_spaces(cls, observation_space, action_space) -> None:  # the core checked them
        return None

    def _build(self) -> None:  # pragma: no cover - never called: the core is built
        raise TypeError("a SharedSlot has no networks of its own; build it with agents.shared.share")

    def _columns(self, columns) -> np.ndarray:
        return np.asarray(columns, np.int64) * self.n_slots + self.slot

    # ---- acting and learning --------------------------------------------------------
    def prepare_envs(self, num_envs: int) -> None:
        self.core.prepare_envs(num_envs * self.n_slots)

    def act(self, obs, deterministic: bool = False):
        return self.core.act(obs, deterministic=deterministic)

    def act_batch(self, obs, columns, deterministic: bool = False) -> np.ndarray:
        return self.core.act_batch(obs, self._columns(columns), deterministic=deterministic)

    def observe_batch(self, obs, actions, rewards, next_obs, terminated, truncated, columns) -> None:
        self.core.observe_batch(obs, actions, rewards, next_obs, terminated, truncated,
                                self._columns(columns))

    def observe_demonstration(self, obs, action, reward, next_obs, terminated, truncated, column: int = 0) -> None:
        """A demonstrated transition of this AC in environment ``column``, as its own column of the core."""
        self.core.observe_demonstration(obs, action, reward, next_obs, terminated, truncated,
                                        column=int(self._columns([column])[0]))

    def update(self) -> dict[str, float]:
        with self.lock:
            return self.core.update()

    # ---- checkpoints: the core's ------------------------------------------------------
    def state_dict(self):
        return self.core.state_dict()

    def load_state_dict(self, state) -> None:
        self.core.load_state_dict(state)

    def save(self, path, policy_only: bool = False, policy_dtype: str = "float32") -> None:
        self.core.save(path, policy_only=policy_only, policy_dtype=policy_dtype)

    def __repr__(self) -> str:
        return f"SharedSlot({self.slot} of {self.n_slots}, core={self.core!r})"


def share(core: Agent, agent_ids: Sequence[str]) -> dict[str, SharedSlot]:
    """One :class:`SharedSlot` of ``core`` per AC id, in order (slot k is ``agent_ids[k]``).

    The core is prepared for one environment (``prepare_envs(len(agent_ids))``), so the slots
    also act and observe one row at a time (``act``/``observe``); the loop prepares it for its
    N environments.

    Raises:
        ValueError: no AC ids, or a core that is itself a slot.
    """
    if not agent_ids:
        raise ValueError("share needs at least one AC id")
    if isinstance(core, SharedSlot):
        raise ValueError("share's core is already a SharedSlot; pass its .core")
    lock = threading.Lock()
    core.prepare_envs(len(agent_ids))
    return {aid: SharedSlot(core, k, len(agent_ids), lock) for k, aid in enumerate(agent_ids)}


def shared_core(agents) -> Agent | None:
    """The one core of a mapping of slots made by :func:`share`, or None when the agents are
    independent (any agent that is not a slot).

    Raises:
        ValueError: slots of more than one core.
    """
    slots = list(agents.values())
    if not slots or not all(isinstance(a, SharedSlot) for a in slots):
        return None
    cores = {id(a.core) for a in slots}
    if len(cores) != 1:
        raise ValueError(f"the agents share {len(cores)} different cores; expected one")
    return slots[0].core
