"""Vectorised multi-agent environments: N PettingZoo ParallelEnvs stepped together.

:class:`VectorEnv` runs N environments, each in its own worker process (the
driving simulator allows one simulation per process), stepping in parallel.
:class:`InProcessVectorEnv` runs them one after the other in this process, with
the same semantics bit for bit (both drive the same :class:`_EnvSlot`): use it
for one environment (``--envs 1``) and in tests. :func:`make_vector_env` picks.

Both return, per agent id ``a`` (an AC slot ``ac_k``), arrays of shape
``(N, ...)`` with one row per environment (:class:`VecStep`):

* ``active[a][i]``: ``a`` acted in env ``i`` this step; only those rows of
  ``rewards``, ``terminated``, ``truncated`` and ``next_obs`` are transitions.
* ``next_obs[a][i]``: the observation that followed the action: the TRUE final
  observation when the agent's episode ended, never a reset observation.
* ``obs[a][i]`` and ``alive[a][i]``: what ``a`` acts on next, and whether it
  acts in env ``i`` at all. An environment whose agents have all finished is
  reset in its worker right away (auto-reset; ``env_reset[i]``), and ``obs``
  then holds the first observation of the new episode.

Observations travel through ``multiprocessing.shared_memory`` (one block per
agent, kind and array, each worker writes its own row; a ``Dict(image, measurements)``
observation is two arrays, and its rows are dicts of them: agents/observations.py);
only actions, rewards, flags and infos are pickled. The arrays in a :class:`VecStep`
are views of that memory, valid until the next ``step``/``step_async``/``reset``: copy
what you keep.
``step_async(actions)`` + ``step_wait()`` (what ``step`` does) let the caller
learn while the workers step (:func:`agents.loop.run_loop` does).
Both take ``envs=[...]`` to step a subset; threads that step DISJOINT sets of
envs may call them concurrently (A3C's learner threads, ``agents/a3c.py``, each
own one env index): each env has its own pipe and its own rows of the shared
arrays, and the in-process version keeps one pending step per env set.

Seeding: ``reset(seed)`` gives env ``i`` its episodes ``k = 0, 1, ...`` the seeds
``seed + i + k * N``, so one environment resets with ``seed, seed + 1, ...``
exactly as :func:`agents.loop.run_loop` does, and a run is reproducible for
the same N and seed.

Shutdown: ``close()`` (also on an exception, Ctrl-C or SIGTERM in the owner)
asks every worker to stop, joins, then terminates and kills stragglers, and
frees the shared memory. Workers ignore SIGINT and die with their owner even
when it is killed with SIGKILL (see ``agents/workers.py``). An exception in a
worker is raised in the parent as :class:`VectorEnvError` naming the env index,
with the worker's traceback.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
import traceback
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from multiprocessing import connection, shared_memory
from typing import Any

import numpy as np

from agents import observations
from agents.workers import WorkerError, _die_with_owner, get_context

__all__ = ["InProcessVectorEnv", "VecStep", "VectorEnv", "VectorEnvError", "make_vector_env"]

logger = logging.getLogger(__name__)

_KINDS = ("obs", "next_obs")


class VectorEnvError(WorkerError):
    """An environment of a vector env failed; ``worker_index`` is the env index."""

    def __init__(self, env_index: int, message: str, worker_traceback: str = ""):
        super().__init__(env_index, f"environment {env_index}: {message}", worker_traceback)
        self.env_index = env_index


@dataclass
class VecStep:
    """What one vector step (or a reset) returns; per agent id, one row per env."""

    obs: dict[str, Any]
    """(N, ...) observation to act on next (a reset observation where ``env_reset``); a dict of
    such arrays for a Dict space."""
    alive: dict[str, np.ndarray]
    """(N,) bool: the agent acts in env i on the next step."""
    next_obs: dict[str, Any]
    """(N, ...) observation that followed this step's action (the true final one when it ended)."""
    active: dict[str, np.ndarray]
    """(N,) bool: the agent acted in env i this step (its row is a transition)."""
    rewards: dict[str, np.ndarray]
    """(N,) float32 rewards (0 where not active)."""
    terminated: dict[str, np.ndarray]
    """(N,) bool."""
    truncated: dict[str, np.ndarray]
    """(N,) bool."""
    env_reset: np.ndarray
    """(N,) bool: env i finished its episode and was reset after this step."""
    infos: list[dict[str, dict]]
    """Per env, agent id -> that env's info for this step (reset infos after a reset)."""
    stepped: np.ndarray
    """(N,) bool: env i took this step (``step_async``/``step_wait`` may step a subset)."""


class _EnvSlot:
    """One environment with auto-reset, writing observations into row arrays.

    ``obs_rows[kind][a]`` is the array this env writes agent ``a``'s observation
    into (a row of a shared-memory block in a worker, of a numpy array in process).
    """

    def __init__(self, env, index: int, num_envs: int, obs_rows: Mapping[str, Mapping[str, np.ndarray]]):
        self.env, self.index, self.num_envs, self.rows = env, index, num_envs, obs_rows
        self.agent_ids = list(env.possible_agents)
        self.seed: int | None = None
        self.episodes = 0

    def _reset(self) -> tuple[np.ndarray, dict]:
        seed = None if self.seed is None else self.seed + self.index + self.episodes * self.num_envs
        obs, infos = self.env.reset(seed=seed)
        if not self.env.agents:
            raise RuntimeError("env.reset() left no live agent; an episode needs at least one")
        for a, o in obs.items():
            observations.assign(self.rows["obs"][a], o)
        return np.array([a in self.env.agents for a in self.agent_ids]), dict(infos)

    def reset(self, seed: int | None) -> tuple[np.ndarray, dict]:
        self.seed, self.episodes = seed, 0
        return self._reset()

    def step(self, actions: Mapping[str, Any]) -> tuple:
        live = list(self.env.agents)
        obs, rewards, terms, truncs, infos = self.env.step({a: actions[a] for a in live})
        n = len(self.agent_ids)
        active, reward = np.zeros(n, bool), np.zeros(n, np.float32)
        term, trunc = np.zeros(n, bool), np.zeros(n, bool)
        for k, a in enumerate(self.agent_ids):
            if a in live:
                active[k], reward[k] = True, float(rewards[a])
                term[k], trunc[k] = bool(terms[a]), bool(truncs[a])
                observations.assign(self.rows["next_obs"][a], obs[a])
                if a in self.env.agents:
                    observations.assign(self.rows["obs"][a], obs[a])
        infos = {a: infos[a] for a in live if a in infos}
        if self.env.agents:
            alive = np.array([a in self.env.agents for a in self.agent_ids])
            return active, reward, term, trunc, alive, False, infos
        self.episodes += 1
        alive, _ = self._reset()
        return active, reward, term, trunc, alive, True, infos


def _spaces(env) -> tuple[list[str], dict, dict]:
    ids = list(env.possible_agents)
    return ids, {a: env.observation_space(a) for a in ids}, {a: env.action_space(a) for a in ids}


class _VectorBase:
    """What both vector envs share: spaces, row arrays and assembling a VecStep."""

    num_envs: int
    agent_ids: list[str]
    observation_spaces: dict
    action_spaces: dict
    arrays: dict[str, dict[str, np.ndarray]]

    @property
    def possible_agents(self) -> list[str]:
        return list(self.agent_ids)

    def observation_space(self, agent: str):
        return self.observation_spaces[agent]

    def action_space(self, agent: str):
        return self.action_spaces[agent]

    def _per_agent(self, table: np.ndarray) -> dict[str, np.ndarray]:
        return {a: table[:, k] for k, a in enumerate(self.agent_ids)}

    def _assemble(self, results: Sequence[tuple], envs: Sequence[int]) -> VecStep:
        """A VecStep of (N, ...) arrays whose rows ``envs`` hold ``results`` (the others: zeros, {})."""
        n, k = self.num_envs, len(self.agent_ids)
        tables = [np.zeros((n, k), np.float32 if j == 1 else bool) for j in range(5)]
        reset, infos = np.zeros(n, bool), [{} for _ in range(n)]
        for i, result in zip(envs, results, strict=True):
            for j in range(5):
                tables[j][i] = result[j]
            reset[i], infos[i] = result[5], result[6]
        active, reward, term, trunc, alive = (self._per_agent(t) for t in tables)
        stepped = np.zeros(n, bool)
        stepped[list(envs)] = True
        return VecStep(obs=self.arrays["obs"], alive=alive, next_obs=self.arrays["next_obs"], active=active,
                       rewards=reward, terminated=term, truncated=trunc, env_reset=reset, infos=infos,
                       stepped=stepped)

    def _envs(self, envs) -> list[int]:
        return list(range(self.num_envs)) if envs is None else [int(i) for i in envs]

    def _assemble_reset(self, results: Sequence[tuple]) -> VecStep:
        alive = self._per_agent(np.stack([r[0] for r in results]))
        n = self.num_envs
        zeros = {a: np.zeros(n, bool) for a in self.agent_ids}
        return VecStep(
            obs=self.arrays["obs"], alive=alive, next_obs=self.arrays["next_obs"], active=zeros,
            rewards={a: np.zeros(n, np.float32) for a in self.agent_ids}, terminated=zeros, truncated=zeros,
            env_reset=np.ones(n, bool), infos=[r[1] for r in results], stepped=np.zeros(n, bool),
        )

    def _split_actions(self, actions: Mapping[str, np.ndarray]) -> list[dict[str, Any]]:
        """``{a: (N, ...) array}`` -> one ``{a: action}`` per env (rows of dead agents are ignored)."""
        out: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        for a, batch in actions.items():
            for i in range(self.num_envs):
                row = batch[i]
                out[i][a] = row.item() if np.ndim(row) == 0 else row
        return out

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class InProcessVectorEnv(_VectorBase):
    """N environments stepped one after the other in this process (same semantics as :class:`VectorEnv`).

    Only one simulator may live in a process, so for the driving env use N = 1.

    Args:
        env_fns: One picklable or plain factory per environment.
    """

    def __init__(self, env_fns: Sequence[Callable[[], Any]]):
        if not env_fns:
            raise ValueError("a vector env needs at least one env factory")
        self.num_envs = len(env_fns)
        self.envs = [fn() for fn in env_fns]
        self.agent_ids, self.observation_spaces, self.action_spaces = _spaces(self.envs[0])
        self.arrays = {
            kind: {a: observations.zeros(s, self.num_envs) for a, s in self.observation_spaces.items()}
            for kind in _KINDS
        }
        self.slots = [
            _EnvSlot(env, i, self.num_envs,
                     {k: {a: observations.take(v, i) for a, v in self.arrays[k].items()} for k in _KINDS})
            for i, env in enumerate(self.envs)
        ]
        self.pids: list[int] = []
        self.groups = [np.arange(self.num_envs)]
        self._pending: dict[tuple[int, ...], list[dict[str, Any]]] = {}
        self._lock = threading.Lock()

    def reset(self, seed: int | None = None) -> VecStep:
        return self._assemble_reset([self._call(i, slot.reset, seed) for i, slot in enumerate(self.slots)])

    groups: list[np.ndarray]
    """Env indices stepped as one group by agents.loop.run_loop: in process, all at once."""

    def step_async(self, actions: Mapping[str, np.ndarray], envs=None) -> None:
        sent = self._envs(envs)
        per_env = self._split_actions(actions)
        with self._lock:  # A3C's learner threads each step their own env index
            self._pending[tuple(sent)] = [per_env[i] for i in sent]

    def step_wait(self, envs=None) -> VecStep:
        with self._lock:
            if envs is None and len(self._pending) == 1:
                key = next(iter(self._pending))
            else:
                key = tuple(self._envs(envs))
            if key not in self._pending:
                raise RuntimeError(f"step_wait({None if envs is None else list(envs)}) without a step_async "
                                   f"for those envs (pending: {[list(k) for k in self._pending]})")
            actions = self._pending.pop(key)
        sent = list(key)
        return self._assemble([self._call(i, self.slots[i].step, a) for i, a in zip(sent, actions, strict=True)],
                              sent)

    def step(self, actions: Mapping[str, np.ndarray]) -> VecStep:
        self.step_async(actions)
        return self.step_wait()

    @staticmethod
    def _call(index: int, fn, arg):
        try:
            return fn(arg)
        except Exception as exc:
            raise VectorEnvError(index, f"{type(exc).__name__}: {exc}", traceback.format_exc()) from exc

    def close(self) -> None:
        for env in self.envs:
            env.close()
        self.envs = []


# ------------------------------------------------------------------------ worker processes
def _env_worker(index: int, num_envs: int, env_fn: Callable[[], Any], conn, owner_pid: int) -> None:
    """Body of an env worker: build the env, attach the shared rows, serve commands."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the owner handles Ctrl-C and tells us to stop
    _die_with_owner(owner_pid)
    blocks: list[shared_memory.SharedMemory] = []
    env = slot = None
    try:
        env = env_fn()
        ids, obs_spaces, act_spaces = _spaces(env)
        conn.send(("spaces", (ids, obs_spaces, act_spaces)))
        names = conn.recv()  # kind -> agent -> part -> block name, or a close command when the owner gave up
        if not isinstance(names, dict):
            return
        rows: dict[str, dict[str, Any]] = {kind: {} for kind in _KINDS}
        for kind in _KINDS:
            for a, part_names in names[kind].items():
                arrays = {}
                for key, space in observations.parts(obs_spaces[a]).items():
                    block = shared_memory.SharedMemory(name=part_names[key])
                    blocks.append(block)
                    arrays[key] = np.ndarray((num_envs, *space.shape), space.dtype, buffer=block.buf)[index]
                rows[kind][a] = observations.join(arrays)
        slot = _EnvSlot(env, index, num_envs, rows)
        while True:
            command, arg = conn.recv()
            if command == "close":
                break
            conn.send(("ok", slot.reset(arg) if command == "reset" else slot.step(arg)))
    except (EOFError, BrokenPipeError):  # the owner went away
        pass
    except BaseException as exc:  # noqa: BLE001 - everything must reach the owner
        try:
            conn.send(("error", (f"{type(exc).__name__}: {exc}", traceback.format_exc())))
        except (OSError, ValueError):
            pass
    finally:
        rows = slot = None  # drop the views before closing the blocks under them
        for block in blocks:
            block.close()
        if env is not None:
            try:
                env.close()
            except Exception:  # noqa: BLE001 - closing after a failure must not mask it
                logger.debug("env %d: close() failed", index, exc_info=True)


class VectorEnv(_VectorBase):
    """N environments, each in its own worker process, stepped in parallel.

    Args:
        env_fns: One picklable factory per environment (top-level functions or
            ``functools.partial`` of them; the env is built inside the worker).
        start_method: ``"spawn"`` or ``"forkserver"`` (``fork`` is refused: unsafe
            with torch threads and one-simulation-per-process simulators).
        timeout_s: Seconds a worker may take for one command (building the env
            included) before the owner gives up with :class:`VectorEnvError`.
        handle_sigterm: While open, turn SIGTERM in the owner into KeyboardInterrupt
            so ``kill <pid>`` cleans up too (main thread only).
    """

    def __init__(self, env_fns: Sequence[Callable[[], Any]], start_method: str = "spawn",
                 timeout_s: float = 600.0, handle_sigterm: bool = True):
        if not env_fns:
            raise ValueError("a vector env needs at least one env factory")
        self.num_envs = len(env_fns)
        self.timeout_s = timeout_s
        self.processes: list = []
        self.conns: list = []
        self.blocks: list[shared_memory.SharedMemory] = []
        self.arrays = {kind: {} for kind in _KINDS}
        self._closed = False
        self._previous_sigterm = None
        if handle_sigterm and threading.current_thread() is threading.main_thread():
            def _interrupt(signum, frame):
                raise KeyboardInterrupt(f"received signal {signum}")
            self._previous_sigterm = signal.signal(signal.SIGTERM, _interrupt)
        context = get_context(start_method, preload=("agents.vector",))
        try:
            for i, fn in enumerate(env_fns):
                parent, child = context.Pipe()
                process = context.Process(target=_env_worker, args=(i, self.num_envs, fn, child, os.getpid()),
                                          name=f"cosim-env-{i}", daemon=True)
                process.start()
                child.close()
                self.processes.append(process)
                self.conns.append(parent)
            spaces = self._gather("building the environment")
            self.agent_ids, self.observation_spaces, self.action_spaces = spaces[0]
            for i, (ids, _, _) in enumerate(spaces):
                if ids != self.agent_ids:
                    raise VectorEnvError(i, f"agents {ids} differ from env 0's {self.agent_ids}")
            names: dict[str, dict[str, dict[str, str]]] = {kind: {} for kind in _KINDS}
            for kind in _KINDS:
                for a, agent_space in self.observation_spaces.items():
                    arrays, names[kind][a] = {}, {}
                    for key, space in observations.parts(agent_space).items():  # one block per array
                        size = max(1, int(np.prod(space.shape)) * np.dtype(space.dtype).itemsize * self.num_envs)
                        block = shared_memory.SharedMemory(create=True, size=size)
                        self.blocks.append(block)
                        names[kind][a][key] = block.name
                        arrays[key] = np.ndarray((self.num_envs, *space.shape), space.dtype, buffer=block.buf)
                    self.arrays[kind][a] = observations.join(arrays)
            for conn in self.conns:
                conn.send(names)
        except BaseException:
            self.close()
            raise

    @property
    def groups(self) -> list[np.ndarray]:
        """Env indices stepped as one group by agents.loop.run_loop: two halves (double buffering:
        one half steps while the trainer acts and learns for the other), or all for N = 1."""
        envs = np.arange(self.num_envs)
        return [envs] if self.num_envs == 1 else [envs[: self.num_envs // 2], envs[self.num_envs // 2:]]

    @property
    def pids(self) -> list[int]:
        """Pids of the env worker processes."""
        return [p.pid for p in self.processes]

    def _gather(self, doing: str, envs: Sequence[int] | None = None) -> list:
        """One reply from each worker of ``envs`` (default all), in env order; a worker's error is raised here."""
        envs = self._envs(envs)
        replies: dict[int, Any] = {}
        deadline = time.monotonic() + self.timeout_s
        waiting = {i: self.conns[i] for i in envs}
        while waiting:
            ready = connection.wait(list(waiting.values()), timeout=1.0)
            for i, conn in list(waiting.items()):
                if conn not in ready:
                    continue
                try:
                    status, payload = conn.recv()
                except (EOFError, OSError):
                    raise VectorEnvError(i, f"worker died while {doing} (exit code {self._exitcode(i)})") from None
                if status == "error":
                    raise VectorEnvError(i, payload[0], payload[1])
                replies[i] = payload
                del waiting[i]
            for i in waiting:
                if not self.processes[i].is_alive():
                    raise VectorEnvError(i, f"worker died while {doing} (exit code {self._exitcode(i)})")
            if waiting and time.monotonic() > deadline:
                raise VectorEnvError(min(waiting), f"no answer after {self.timeout_s:.0f} s while {doing}")
        return [replies[i] for i in envs]

    def _exitcode(self, index: int):
        self.processes[index].join(timeout=1.0)
        return self.processes[index].exitcode

    def _send(self, messages: Sequence[tuple], envs: Sequence[int] | None = None) -> None:
        for i, message in zip(self._envs(envs), messages, strict=True):
            try:
                self.conns[i].send(message)
            except (BrokenPipeError, OSError):
                raise VectorEnvError(i, f"worker is gone (exit code {self._exitcode(i)})") from None

    def _broadcast(self, messages: Sequence[tuple], doing: str) -> list:
        self._send(messages)
        return self._gather(doing)

    def reset(self, seed: int | None = None) -> VecStep:
        return self._assemble_reset(self._broadcast([("reset", seed)] * self.num_envs, "resetting"))

    def step_async(self, actions: Mapping[str, np.ndarray], envs=None) -> None:
        """Send the actions to ``envs`` (default all); they step while the caller acts or learns."""
        envs = self._envs(envs)
        per_env = self._split_actions(actions)
        self._send([("step", per_env[i]) for i in envs], envs)

    def step_wait(self, envs=None) -> VecStep:
        """The result of :meth:`step_async` for ``envs`` (default all): only their rows are filled."""
        envs = self._envs(envs)
        return self._assemble(self._gather("stepping", envs), envs)

    def step(self, actions: Mapping[str, np.ndarray]) -> VecStep:
        self.step_async(actions)
        return self.step_wait()

    def close(self, join_timeout: float = 5.0) -> None:
        """Stop, join, terminate, then kill every worker; free the shared memory. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            for conn in self.conns:
                try:
                    conn.send(("close", None))
                except (OSError, ValueError):
                    pass
            deadline = time.monotonic() + join_timeout
            for process in self.processes:
                process.join(timeout=max(0.0, deadline - time.monotonic()))
            for process in self.processes:
                if process.is_alive():
                    logger.warning("env worker pid %d did not stop in time; terminating", process.pid)
                    process.terminate()
                    process.join(timeout=1.0)
                if process.is_alive():
                    process.kill()
                    process.join(timeout=1.0)
            for conn in self.conns:
                conn.close()
        finally:
            self.arrays = {kind: {} for kind in _KINDS}
            for block in self.blocks:
                block.close()
                try:
                    block.unlink()
                except FileNotFoundError:
                    pass
            self.blocks = []
            if self._previous_sigterm is not None:
                signal.signal(signal.SIGTERM, self._previous_sigterm)
                self._previous_sigterm = None

    def __del__(self):
        if not getattr(self, "_closed", True):
            self.close()


def make_vector_env(env_fns: Sequence[Callable[[], Any]], processes: bool | None = None,
                    start_method: str = "spawn") -> InProcessVectorEnv | VectorEnv:
    """A :class:`VectorEnv` (worker processes) or, by default for one env, an :class:`InProcessVectorEnv`."""
    if processes is None:
        processes = len(env_fns) > 1
    return VectorEnv(env_fns, start_method=start_method) if processes else InProcessVectorEnv(env_fns)
