"""A training run's options, declared once: :class:`RunOptions`.

Each field of RunOptions is one option of a run, declared with :func:`option`: its default,
its ``--help`` line, its flag, the values it accepts (checked in ``__post_init__``, the
message naming the flag), whether `cosim benchmark` takes it too (``benchmark``: one value
for every trial of the grid) and whether the report says it of each tested checkpoint's run
(``report``). Everything else is derived from these fields:

- the flags of `cosim train` and `cosim benchmark` (:func:`add_flags`, :meth:`RunOptions.from_args`);
- ``make_config``'s keyword parameters and the TrainConfig it resolves
  (eval.training.config.resolve, which fills the TrainConfig keys a field names in ``config``);
- the run options of a benchmark's trials (eval.scale.benchmark.BenchmarkPlan.options);
- the options each run of ``--algo all`` is started with (:meth:`RunOptions.for_algo`, handed to
  the child process as :meth:`RunOptions.to_json`) and the TrainConfig each ``--pbt`` trial trains;
- the report's keys of a run's training (:func:`report_keys`).

Adding an option is one field here plus the code that uses it (the TrainConfig field it fills,
the trainer's use of it); adding a choice to ``--obs`` or ``--collisions`` is one value in its
tuple (cosim.wrappers.OBS_VARIANTS, :data:`COLLISION_RULES`). tests/eval/test_run_options.py
walks every field through `cosim train`, `cosim benchmark`, ``--algo all``, ``--pbt`` and the report.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from agents import registry
from cosim.errors import CosimError
from cosim.wrappers import OBS_VARIANTS
from eval.labels import ENVS

__all__ = ["COLLISION_RULES", "DEVICES", "FAULT_RULES", "MAX_SEED", "Option", "RunOptions", "SELECTION_RULES", "TrainError", "add_flags",
           "benchmark_names", "declared", "int_in", "names_text", "option", "parse_set", "report_keys"]


class TrainError(CosimError, ValueError):
    """A training request that cannot run; the message says what to change."""


ALGORITHMS: tuple[str, ...] = tuple(registry.ALGORITHMS)
COLLISION_RULES = ("event", "step", "end")
"""``--collisions``: ``event`` (the default, the test's rule): the episode goes on after a
collision and each collision event is charged once; ``step``: the episode goes on and every
contact step is charged (task version 3); ``end``: a collision ends the AC's training episode
(the paper's rule). TrainConfig.collision_charge and .collisions_end_episode; docs/task.md,
"Collision rule"."""
FAULT_RULES = ("at_fault", "both")
"""``--fault``: who of a vehicle contact the reward charges: ``at_fault`` (the default since task
version 5), the car that drove into the other; ``both`` (task version 4), every car in it.
TrainConfig.collision_fault, cosim.scenario.Contact.fault; docs/task.md, "Collision rule"."""
SELECTION_RULES = ("return", "ds")
"""``--select-by``: what picks each AC's best.pt among its validated checkpoints: ``return`` (the
default), the mean undiscounted return; ``ds``, the mean driving score, the test's headline metric
(tried on the state track, lower held-out scores: docs/task.md, "Checkpoint selection").
TrainConfig.select_by."""
DEVICES = ("auto", "cpu", "cuda")
"""``--device``: the learners' torch device (auto: cuda when available)."""
MAX_SEED = 2**31 - 1
"""The largest seed: SUMO's seeds are below 2^31 (and torch's generators take < 2^64)."""
REPORT_SETTINGS = ("horizon", "image_size")
"""TrainConfig keys the report gives beside the options': the episode length and the camera's
pixels, which the preset and the network fix (no flag sets them)."""


def int_in(low: int, high: int | None = None):
    """An argparse type: an int in [low, high]; the error names the value and the range."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
        if value < low or (high is not None and value > high):
            raise argparse.ArgumentTypeError(f"must be {_span(low, high)}, got {value}")
        return value

    return parse


def _span(low: int, high: int | None) -> str:
    return f"{low}..{high}" if high is not None else f">= {low}"


def names_text(envs: Sequence[str]) -> str:
    """``env_1..env_5`` for the bundled environments (a run of names), else the names listed."""
    return f"{envs[0]}..{envs[-1]}" if len(envs) > 2 else ", ".join(envs)


def parse_set(items: Sequence[str]) -> dict[str, str]:
    """``["lr=3e-4", ...]`` (``--set`` arguments) -> ``{"lr": "3e-4"}``; values stay text."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise TrainError(f"--set {item!r}: write FIELD=VALUE, e.g. --set learning_rate=3e-4")
        out[key.strip()] = value.strip()
    return out


@dataclass(frozen=True)
class Option:
    """How one RunOptions field is given and where it goes (the field's ``metadata["option"]``)."""

    flag: str
    """The command-line flag, e.g. ``--frame-stack``."""
    help: str
    """Its ``--help`` line (the formatter adds the default unless this says it)."""
    low: int | None = None
    """A whole number's smallest value (argparse's type and ``__post_init__`` check it); None: not a number."""
    high: int | None = None
    """A whole number's largest value (None: no limit)."""
    choices: Sequence[str] | None = None
    """The values a text option accepts."""
    note: str = ""
    """Said after the range when a value is refused, e.g. `` (0: off)``."""
    metavar: str | None = None
    path: bool = False
    """A file or folder: argparse gives a Path, the options hold its text."""
    repeat: bool = False
    """Given once per item (``--set``): argparse appends, the options hold a mapping."""
    benchmark: bool = False
    """`cosim benchmark` takes it too, one value for every trial (BenchmarkPlan.options)."""
    benchmark_help: str | None = None
    """The benchmark's help line where it says more than the train one (None: the same)."""
    benchmark_default: Any = None
    """The benchmark's default where it differs from the field's (None: the same)."""
    report: bool = False
    """The report says it of each tested checkpoint's run (:func:`report_keys`)."""
    config: tuple[str, ...] | None = None
    """The TrainConfig keys it sets (None: the one of its own name); ``()``: none, it is checked only."""

    def refusal(self, value: Any) -> str | None:
        """Why ``value`` is not one this option accepts (None: it is)."""
        if value is None:
            return None
        if self.choices is not None and value not in self.choices:
            return f"{self.flag} must be {' or '.join(self.choices)}, got {value!r}"
        if self.low is not None:
            if not isinstance(value, int) or isinstance(value, bool):
                return f"{self.flag} must be a whole number, got {value!r}"
            if value < self.low or (self.high is not None and value > self.high):
                return f"{self.flag} must be {_span(self.low, self.high)}{self.note}, got {value}"
        return None


def option(default: Any, flag: str, help: str, **how: Any) -> Any:
    """A RunOptions field: its default and its :class:`Option` (flag, help, checks, where it goes)."""
    spec = Option(flag=flag, help=help, **how)
    if isinstance(default, dict):
        return field(default_factory=dict, metadata={"option": spec})
    return field(default=default, metadata={"option": spec})


@dataclass(frozen=True)
class RunOptions:
    """The options of one training run (or of ``--algo all``): what `cosim train` is told,
    before the preset fills in what it leaves open (eval.training.config.resolve -> TrainConfig)."""

    algo: str = option("ppo", "--algo", f"{', '.join(ALGORITHMS)}, or all (every one, in parallel where CPUs "
                       "allow)", report=True)
    env: str = option("env_1", "--env", f"{names_text(ENVS)} or a scenario .yaml", report=True)
    preset: str = option(
        "quick", "--preset", "run preset, from eval/training/hyperparams/runs.yaml", report=True,
        benchmark=True, benchmark_default="standard",
        benchmark_help="run preset (eval/training/hyperparams/runs.yaml): standard for a study, smoke to check "
                       "the pipeline (the same grid with short trials; how long each takes: docs/benchmarks.md)")
    agents: int | None = option(None, "--agents", "learning cars (default: from the preset)", low=1, metavar="N",
                                benchmark=True, report=True,
                                benchmark_help="ACs each trial trains (default: the preset's)")
    steps: int | None = option(
        None, "--steps", "environment steps (default: from the preset); with --resume, the run's new budget",
        low=1, benchmark=True, report=True, benchmark_help="environment steps per trial (default: the preset's)")
    seed: int = option(0, "--seed", "seed of the run (environments, weights, exploration)", low=0, high=MAX_SEED,
                       report=True)
    action_type: str | None = option(
        None, "--action-type", f"must match the algorithm (discrete: {' '.join(registry.DISCRETE)}; default: the "
        "algorithm's own)", choices=("discrete", "continuous"), config=())
    agent_preset: str | None = option(None, "--agent-preset", "hyperparameters: default or paper (default: the "
                                      "run preset's)", config=("agent_config",))
    hyper: dict[str, str] = option(
        {}, "--set", "change one agent hyperparameter, e.g. --set learning_rate=3e-4 (repeatable)",
        metavar="FIELD=VALUE", repeat=True, config=("agent_config",))
    envs: int | None = option(
        None, "--envs", "environments stepped together, one process each when > 1, every algorithm (default: the "
        "preset's envs; a3c/impala: its workers)", low=1)
    frame_stack: int | None = option(
        None, "--frame-stack", "camera frames per observation, stacked oldest first (84x84x3K; default: the "
        "preset's, 1 = the paper's single frame); tests of the run stack K too", low=1,
        note=" (1: a single camera frame)", metavar="K", report=True)
    obs: str = option(
        "image", "--obs", "what an AC observes: image (default: its camera frames, the paper's), nav (the frames "
        "beside speed, route command and distance to the goal), state (65 numbers: route geometry, goal, signal, "
        "nearest cars and people; cameras off, frame stack 1) or route (the frames with the AC's own next 40 m of "
        "route drawn on the ground; docs/task.md, Observation); tests of the run build the same for its ACs", choices=OBS_VARIANTS, benchmark=True, report=True,
        benchmark_help=f"what the trials' ACs observe (as `cosim train --obs`: {', '.join(OBS_VARIANTS)}; default "
                       "image, the paper's)")
    collisions: str = option(
        "event", "--collisions", "event (default): as in the test, the episode goes on and each collision event is "
        "charged once; step: every contact step is charged (task version 3); end: a collision ends the AC's training "
        "episode (the paper's rule; docs/task.md, Collision rule)", choices=COLLISION_RULES, benchmark=True,
        report=True, config=("collisions_end_episode", "collision_charge"),
        benchmark_help="training episodes at a collision (as `cosim train --collisions`; default event: the test's "
                       "rule, docs/task.md)")
    fault: str = option(
        "at_fault", "--fault", "who of a car contact the reward charges: at_fault (default: the car that drove "
        "into the other) or both (every car in it, task version 4); the test's driving score counts every event "
        "either way (docs/task.md, Collision rule)", choices=FAULT_RULES, benchmark=True, report=True,
        config=("collision_fault",),
        benchmark_help="who of a car contact the trials' reward charges (as `cosim train --fault`; default at_fault)")
    share_params: bool = option(
        False, "--share-params", "the run's ACs act with ONE network that learns from all their transitions "
        "(parameter sharing; default: one network per AC, the paper's; ppo dqn ddpg td3; docs/agents.md)",
        benchmark=True, report=True,
        benchmark_help="one network per trial for all its ACs in ppo dqn ddpg td3 (as `cosim train --share-params`; "
                       "a3c and impala stay one per AC; default: one per AC)")
    stall_truncate: int = option(
        0, "--stall-truncate", "truncate a training episode once every AC has stood still N steps away from a red "
        "light: more attempts per env step, the test's rewards (default 0: off; docs/task.md, Collision rule)",
        low=0, note=" steps (0: off)", metavar="N", report=True)
    demo_steps: int = option(
        0, "--demo-steps", "dqn ddpg td3: first drive N env steps (whole episodes) with the scripted autopilot and "
        "put every AC's transitions in its replay as demonstrations; not counted in --steps (default 0: none; "
        "docs/agents.md, Demonstrations)", low=0, note=" (0: off)", metavar="N", benchmark=True, report=True,
        benchmark_help="the demonstration variant: dqn ddpg td3 trials put N env steps of the autopilot's driving "
                       "in their replays, pre-train on them and learn with the variant's losses (docs/agents.md, "
                       "Demonstrations); default 0: off")
    demo_updates: int = option(
        0, "--demo-updates", "with --demo-steps: N gradient steps on the demonstrations before the first env step "
        "(DQfD's pre-training; default 0); their losses: dqn --set demo_margin=0.8, ddpg td3 --set demo_bc=W",
        low=0, note=" (0: off)", metavar="N", report=True)
    encoder: str | None = option(
        None, "--encoder", "a frozen perception encoder file (`cosim encoder train`): each AC observes the encoder's 512 "
        "features of each of its K camera frames and learns MLP heads (the preset's state_hidden) on them, replay "
        "holding features; camera observations only (not --obs nav or state); the run records the file's sha256 "
        "and its tests refuse another (default: none, the CNN learns end to end; docs/task.md)",
        path=True, metavar="FILE", benchmark=True, report=True, config=("encoder", "encoder_sha256"),
        benchmark_help="every trial learns heads on this frozen perception encoder's features (as `cosim train "
                       "--encoder`; default: none)")
    init_from: str | None = option(
        None, "--init-from", "warm start: each AC's policy weights from this run folder (its ac_k/best.pt) or "
        "checkpoint file, optimizers fresh (a curriculum; default: random weights; docs/agents.md)",
        path=True, metavar="RUN_OR_CKPT", report=True)
    validation_episodes: int | None = option(
        None, "--validation-episodes", "held-out episodes under the test's rules at every checkpoint that pick each "
        "AC's best.pt (default: the preset's, else 2; 0: off, best.pt by training return; docs/task.md)",
        low=0, note=" (0: off)", metavar="N", report=True)
    validation_steps: int | None = option(
        None, "--validation-steps", "steps per validation episode (default: the preset's horizon, at most the "
        "scenario's: quick 300, standard 600)", low=1, metavar="STEPS", report=True)
    select_by: str = option(
        "return", "--select-by", "what picks each AC's best.pt on the validation episodes: return (default: the "
        "mean undiscounted return) or ds (the mean driving score, the test's headline); docs/task.md, Checkpoint "
        "selection", choices=SELECTION_RULES, benchmark=True, report=True,
        benchmark_help="what picks each trial AC's best.pt on validation (as `cosim train --select-by`; default "
                       "return)")
    device: str = option("auto", "--device", "torch device of the learners (auto: cuda when available)",
                         choices=DEVICES)
    torch_threads: int = option(0, "--torch-threads", "torch threads in the trainer (0: the CPUs the env workers "
                                "leave, shared among the learner threads)", low=0, metavar="K")
    learner_threads: int = option(0, "--learner-threads", "ACs updating at once on K threads (0: one per AC up to "
                                  "the CPUs); the result is the same for any K", low=0, metavar="K")

    def __post_init__(self):
        if self.algo not in (*ALGORITHMS, "all"):
            raise TrainError(f"unknown algorithm {self.algo!r}; choose one of {', '.join(ALGORITHMS)} (or 'all')")
        hyper = self.hyper
        if not isinstance(hyper, Mapping):  # the command line's FIELD=VALUE texts
            hyper = parse_set(hyper)
        object.__setattr__(self, "hyper", {str(k): str(v) for k, v in hyper.items()})
        for name in ("init_from", "encoder"):  # a Path from the command line: its text
            if getattr(self, name) is not None:
                object.__setattr__(self, name, str(getattr(self, name)))
        for name, spec in declared():
            problem = spec.refusal(getattr(self, name))
            if problem:
                raise TrainError(problem)

    @property
    def algos(self) -> tuple[str, ...]:
        """The algorithms these options train: every one for ``--algo all``, else the one."""
        return ALGORITHMS if self.algo == "all" else (self.algo,)

    def replace(self, **changes: Any) -> RunOptions:
        """These options with some changed (checked again)."""
        return dataclasses.replace(self, **changes)

    def for_algo(self, algo: str) -> RunOptions:
        """The options of ``algo``'s run among several (``--algo all``, a benchmark's grid): A3C and
        IMPALA build their own learners, so parameter sharing is dropped for them."""
        return self.replace(algo=algo, share_params=self.share_params and algo not in registry.ASYNC)

    def changed(self, names: Sequence[str] | None = None) -> dict[str, Any]:
        """The options (of ``names``, default all) that differ from their defaults, by name."""
        default = RunOptions()
        return {n: getattr(self, n) for n, _ in declared() if (names is None or n in names)
                and getattr(self, n) != getattr(default, n)}

    def to_json(self) -> str:
        """These options as one JSON object (what an ``--algo all`` run is started with)."""
        return json.dumps(dataclasses.asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> RunOptions:
        """The options :meth:`to_json` wrote.

        Raises:
            TrainError: not a JSON object, or a key that is no option (listing the valid ones).
        """
        try:
            data = json.loads(text)
        except ValueError as exc:
            raise TrainError(f"--options: not valid JSON ({exc})") from None
        if not isinstance(data, dict):
            raise TrainError(f"--options: expected a JSON object of run options, got {type(data).__name__}")
        valid = [n for n, _ in declared()]
        unknown = sorted(set(data) - set(valid))
        if unknown:
            raise TrainError(f"--options: unknown option(s) {unknown}; valid: {', '.join(valid)}")
        return cls(**data)

    @classmethod
    def from_args(cls, args: argparse.Namespace, command: str = "train") -> RunOptions:
        """The options a parsed command line gives (the flags :func:`add_flags` added for ``command``)."""
        given = {n: getattr(args, n) for n, spec in declared() if command == "train" or spec.benchmark}
        return cls(**{n: str(v) if isinstance(v, Path) else v for n, v in given.items()})


def declared() -> tuple[tuple[str, Option], ...]:
    """Every RunOptions field's name and :class:`Option`, in declaration order."""
    return tuple((f.name, f.metadata["option"]) for f in dataclasses.fields(RunOptions))


def benchmark_names() -> tuple[str, ...]:
    """The options `cosim benchmark` takes (declared ``benchmark``), in declaration order."""
    return tuple(n for n, spec in declared() if spec.benchmark)


def config_keys(name: str) -> tuple[str, ...]:
    """The TrainConfig keys option ``name`` sets."""
    spec = dict(declared())[name]
    return (name,) if spec.config is None else spec.config


def report_keys() -> tuple[str, ...]:
    """The config.yaml keys the report gives of each tested checkpoint's run: those of the options
    declared ``report``, and :data:`REPORT_SETTINGS`."""
    keys = [k for n, spec in declared() if spec.report for k in config_keys(n)]
    return (*keys, *REPORT_SETTINGS)


def add_flags(parser: argparse.ArgumentParser, command: str,
              choices: Mapping[str, Sequence[str] | None] | None = None) -> None:
    """Add the flags of the options ``command`` takes (``train``: all, ``benchmark``: those declared
    ``benchmark``, with its help and default) to ``parser``; ``choices`` overrides an option's
    choices (the presets' names, which the CLI reads from the YAML)."""
    defaults = {f.name: (f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default)
                for f in dataclasses.fields(RunOptions)}
    for name, spec in declared():
        if command == "benchmark" and not spec.benchmark:
            continue
        bench = command == "benchmark"
        default = spec.benchmark_default if bench and spec.benchmark_default is not None else defaults[name]
        how: dict[str, Any] = {"dest": name, "help": (spec.benchmark_help if bench else None) or spec.help}
        if isinstance(default, bool):
            parser.add_argument(spec.flag, action="store_true", **how)
            continue
        if spec.repeat:
            how.update(action="append", default=[], metavar=spec.metavar)
        else:
            kind = Path if spec.path else int_in(spec.low, spec.high) if spec.low is not None else None
            listed = (choices or {}).get(name, spec.choices)
            how.update(default=default, type=kind, metavar=spec.metavar, choices=listed or None)
        parser.add_argument(spec.flag, **how)
