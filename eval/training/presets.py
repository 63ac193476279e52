"""Run presets (smoke, quick, standard, paper: the names in runs.yaml) read from YAML, rl-zoo style.

``eval/training/hyperparams/runs.yaml`` holds what every algorithm of a preset shares (ACs,
episode horizon, checkpoint interval, agent preset, workers, envs, frame stack);
``eval/training/hyperparams/<algo>.yaml`` holds, per preset, the algorithm's step budget and
the hyperparameters it changes on top of the agent preset (the agent config
dataclass's ``PRESETS``, e.g. ``TD3Config`` in agents/configs.py). Adding an algorithm
to the catalogue (agents/registry.py) means adding its YAML here; unknown keys
are refused with the list of valid ones.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from agents.registry import ALGORITHMS, POLICY_DTYPES
from cosim.errors import CosimError

__all__ = ["HYPERPARAMS", "PresetError", "TrainPreset", "load_presets", "preset_names"]

HYPERPARAMS = Path(__file__).with_name("hyperparams")
"""The folder of the preset YAML files (package data)."""


@dataclass(frozen=True)
class TrainPreset:
    """Budgets and sizes of a family of runs."""

    steps: dict[str, int]
    """Environment steps per algorithm."""
    agents: int
    """Learning cars trained together."""
    horizon: int
    """Steps per training episode before truncation: the one source of a run's episode length
    (TrainConfig.horizon; its validation episodes take it too, at most the scenario's horizon)."""
    checkpoint_every: int
    """Environment steps between checkpoints."""
    agent_preset: str
    """The agents' hyperparameter preset ("default" or "paper")."""
    workers: int
    """A3C's and IMPALA's environments when ``--envs`` is not given (one vector env;
    A3C runs one learner thread per environment)."""
    frame_stack: int
    """Camera frames per observation (1: the paper's single frame; runs.yaml gives 4, the paper's
    released scripts' stack, and is the one source of it); ``--frame-stack`` overrides it
    (eval/training/config.py TrainConfig.frame_stack)."""
    overrides: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Per-algorithm hyperparameter changes on top of agent_preset."""
    state_overrides: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Per-algorithm changes on top of ``overrides`` for the state track (``--obs state``), from
    an <algo>.yaml entry's ``state_hyperparameters``: a gradient step of its MLPs costs a fraction
    of the CNN's, so the update-to-data ratio sized for the camera is not the state track's
    (DQN's ``train_freq: 2``, docs/reference.md#presets)."""
    envs: int = 1
    """Environments stepped together by PPO, DQN, DDPG and TD3 (A3C and IMPALA default
    to ``workers`` environments instead); ``cosim train --envs`` overrides both."""
    validation_episodes: int | None = None
    """Held-out validation episodes per checkpoint that pick best.pt (None: the library's
    default, eval/training/config.py VALIDATION_EPISODES); ``--validation-episodes`` overrides it."""
    reward_scale: float = 0.01
    """Every algorithm learns on reward x this: the driving reward is worth up to ~24
    per step and -50 per collision, so unscaled returns run to thousands and the value
    loss swamps the policy's gradients in the shared CNN (PPO collapsed without it)."""
    policy_dtype: str = "float32"
    """How each AC's best.pt (the policy the test drives) stores its float weights: float32,
    exact, or float16, half the bytes and rounded (agents.checkpoint.POLICY_DTYPES). Only the
    smoke preset takes float16: its 60 policy files would otherwise be ~385 MB for numbers that
    check the pipeline, not the algorithms (docs/benchmarks.md#disk-per-run-and-per-preset)."""
    state_hidden: tuple[int, ...] = (256, 256)
    """Hidden sizes of every algorithm's MLPs on the state track (``--obs state``, cosim.state:
    65 numbers; each config's ``hidden``, 64x64 for PPO, A3C and IMPALA otherwise): the
    MetaDrive / highway-env scale for a vector of nearby actors. An algorithm's YAML that sets
    ``hidden`` wins; ``--set hidden=[...]`` wins over both."""



_ALGO_KEYS = ("steps", "hyperparameters", "state_hyperparameters")


class PresetError(CosimError, ValueError):
    """A preset YAML in ``eval/training/hyperparams/`` is missing, not YAML, or holds an unknown key or
    value; the message names the file and the fix. The CLI reports it as one line (exit 2) for
    the commands that read the presets, train and benchmark; the others work
    (docs/reference.md#exit-codes-and-errors)."""

    def __init__(self, path: Path, problem: str):
        path = Path(path)
        restore = (f" (or restore it: git checkout -- eval/training/hyperparams/{path.name})"
                   if path.parent.resolve() == HYPERPARAMS.resolve() else "")
        super().__init__(f"{path}: {problem}; fix that file{restore}; the format is in "
                         "docs/reference.md#presets")


def _read(path: Path) -> dict[str, dict[str, Any]]:
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise PresetError(path, f"cannot read it ({exc.strerror or exc})") from None
    except yaml.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        line = f" at line {where.line + 1}" if where is not None else ""
        raise PresetError(path, f"not valid YAML{line} ({getattr(exc, 'problem', None) or exc})") from None
    if not isinstance(data, dict) or not all(isinstance(v, dict) for v in data.values()):
        raise PresetError(path, "expected a mapping of preset name -> settings")
    return data


def _check_keys(path: Path, where: str, keys, valid) -> None:
    unknown = sorted(set(keys) - set(valid))
    if unknown:
        raise PresetError(path, f"{where}: unknown key(s) {unknown}; valid keys: {sorted(valid)}")


def preset_names() -> tuple[str, ...]:
    """The run presets' names in runs.yaml order (what ``--preset`` accepts)."""
    return tuple(load_presets())


@functools.cache
def load_presets(folder: Path = HYPERPARAMS) -> dict[str, TrainPreset]:
    """The run presets, by name, from ``folder``'s runs.yaml and <algo>.yaml files.

    Raises:
        PresetError: (a ValueError and a CosimError) a missing or unreadable file, bad YAML,
            an unknown key (listing the valid ones), or an algorithm without a step budget
            for a preset; the message names the file and the fix.
    """
    folder = Path(folder)
    runs = _read(folder / "runs.yaml")
    shared = [f.name for f in dataclasses.fields(TrainPreset) if f.name not in ("steps", "overrides", "state_overrides")]
    per_algo = {algo: _read(folder / f"{algo}.yaml") for algo in ALGORITHMS}
    presets = {}
    for name, settings in runs.items():
        _check_keys(folder / "runs.yaml", name, settings, shared)
        steps, overrides, state_overrides = {}, {}, {}
        for algo, entries in per_algo.items():
            path = folder / f"{algo}.yaml"
            _check_keys(path, "presets", entries, runs)
            entry = entries.get(name)
            if entry is None or "steps" not in entry:
                raise PresetError(path, f"preset {name!r} needs 'steps' (environment steps)")
            _check_keys(path, name, entry, _ALGO_KEYS)
            try:
                steps[algo] = int(entry["steps"])
            except (TypeError, ValueError):
                raise PresetError(path, f"{name}: steps must be a whole number of environment "
                                        f"steps, got {entry['steps']!r}") from None
            if entry.get("hyperparameters"):
                overrides[algo] = dict(entry["hyperparameters"])
            if entry.get("state_hyperparameters"):
                state_overrides[algo] = dict(entry["state_hyperparameters"])
        if settings.get("policy_dtype", "float32") not in POLICY_DTYPES:
            raise PresetError(folder / "runs.yaml", f"{name}: policy_dtype must be one of "
                                                    f"{', '.join(POLICY_DTYPES)}, got {settings['policy_dtype']!r}")
        required = [f.name for f in dataclasses.fields(TrainPreset) if f.name not in ("steps", "overrides", "state_overrides")
                    and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
        missing = [key for key in required if key not in settings]
        if missing:
            raise PresetError(folder / "runs.yaml", f"{name}: missing key(s) {missing}; every preset gives "
                                                    f"{', '.join(required)}")
        if "state_hidden" in settings:
            settings = {**settings, "state_hidden": tuple(settings["state_hidden"])}
        presets[name] = TrainPreset(steps=steps, overrides=overrides, state_overrides=state_overrides, **settings)
    return presets
