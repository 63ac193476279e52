"""The `cosim` command line: the top layer: the only place that wires environments, agents and evaluation.

The parser and one error and exit policy (:func:`main`) are here, the handlers in
eval/cli/learn.py and eval/cli/sim.py; ``python -m eval.cli`` runs :func:`main` (__main__.py).
What `cosim --help` says cosim is: :data:`DESCRIPTION`; its list of commands (the epilog):

    cosim scenarios                         list the driving environments
    cosim drive env_3 --agents 6            run the scripted drivers, print events (no cameras)
    cosim view env_3 --out view/            camera mosaic PNG + GIFs of what the ACs see
    cosim nets build | check                rebuild / check the SUMO networks
    cosim train --algo ppo --env env_1      train N ACs of one algorithm together
    cosim test --agents 6                   the test protocol (Scenario 1 and 2) and its report
    cosim benchmark --preset smoke          train the grid on Ray Tune, test it, write the report
    cosim encoder train --out enc.pt        build the frozen perception encoder (--encoder)
    cosim replay REPORT/replays/X/state.json  reopen a failure replay's SUMO state
    cosim check-scenarios env_4             degenerate-policy suite: does a scenario measure driving?
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from eval.cli import encoder, learn, sim
from eval.training.options import MAX_SEED, int_in, names_text


def main(argv: list[str] | None = None) -> int:
    """Run one command; the exit code follows one policy (docs/reference.md#exit-codes-and-errors):
    0 done, 2 a user error (argparse's usage errors, and any error a user can cause:
    ``cosim.errors.CosimError``, ``agents.errors.AgentError``), 1 a bug or a failed check
    (check-scenarios), 130 interrupted, 141 its output's reader went away (a closed pipe)."""
    from agents.errors import AgentError
    from cosim.errors import CosimError

    try:
        # inside the try, though a bad preset YAML does not stop it: the commands that read the
        # presets (train, benchmark) raise its error when run, the others work (_preset_names)
        parser = build_parser()
        args = parser.parse_args(argv)
        logging.basicConfig(level=logging.WARNING if not args.verbose else logging.INFO,
                            format="%(levelname)s %(name)s: %(message)s")
        if not hasattr(args, "func"):
            parser.print_help()
            return USAGE
        return int(args.func(args) or 0)
    except (CosimError, AgentError) as exc:
        # the roots of cosim (eval's errors subclass it) and of agents: the message names the
        # input and the fix; a multi-line one (a worker's traceback) goes to a log file
        lines = str(exc).strip().splitlines() or [type(exc).__name__]
        more = f" (details in {_write_log(str(exc))})" if len(lines) > 1 else ""
        print(f"cosim: error: {lines[0]}{more}", file=sys.stderr)
        return USAGE
    except KeyboardInterrupt:
        print("cosim: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader went away (`cosim ... | head`): as the shell's tools, no message
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # Python's flush at exit would raise again
        return 141
    except Exception as exc:  # a bug: one line here, the traceback in a log file
        import traceback

        path = _write_log(traceback.format_exc())
        first = (str(exc).strip().splitlines() or [""])[0][:200]
        print(f"cosim: unexpected error {type(exc).__name__}: {first} (traceback in {path}; "
              "please report it)", file=sys.stderr)
        return 1


USAGE = 2
"""The exit code of every user error: argparse's (a bad command line) and the errors a user
can cause (bad input, a refused option or resume, a missing optional dependency); 1 is a bug
or a failed check, so a script can tell "fix the input" from "cosim failed"."""


KEPT_LOGS = 20
"""Error logs kept in the log folder (:func:`_write_log`): the newest; older ones are removed."""


def _write_log(text: str) -> Path | str:
    """Write `text` to a fresh log file and return its path: in this user's private folder
    ``<temp>/cosim-errors-<uid>`` (``cosim.tempfiles.private_folder``: mode 0700, never a link),
    created exclusively under a name no one can take first; the :data:`KEPT_LOGS` newest are kept."""
    import datetime as dt
    import tempfile

    from cosim.tempfiles import private_folder

    def age(path: Path) -> int:
        try:
            return -path.stat().st_mtime_ns
        except OSError:  # removed meanwhile by another cosim
            return 0

    try:
        folder = private_folder(f"cosim-errors-{os.getuid()}")
        stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        fd, name = tempfile.mkstemp(prefix=f"cosim-error-{stamp}-{os.getpid()}-", suffix=".log", dir=folder)
        with os.fdopen(fd, "w") as f:
            f.write(f"cosim {' '.join(sys.argv[1:])}\n{text}")
        for old in sorted(folder.glob("cosim-error-*.log"), key=age)[KEPT_LOGS:]:
            old.unlink(missing_ok=True)
    except OSError as exc:  # a full disk: the message must still come out
        return f"no log file: {exc.strerror or exc}"
    return Path(name)


DESCRIPTION = (
    "cosim: an open benchmark for multi-agent deep reinforcement learning in urban driving. "
    "SUMO traffic and PyBullet cameras run in co-simulation; autonomous cars (ACs) learn to drive "
    "from their camera with six algorithms (PPO, A3C, IMPALA, DQN, DDPG, TD3) in five "
    "environments; a test protocol measures them together and alone and writes a report.")
EXAMPLES = "commands, as a first session runs them:\n" + "\n".join(
    line for line in __doc__.splitlines() if line.startswith("    cosim "))


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Every option's help line ends with its default, ``(default: X)``, unless the help
    already says it; a flag (store_true) is off by default and says nothing. The
    description and the epilog keep their line breaks (the command list)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if ("default" in text or action.default is argparse.SUPPRESS or action.nargs == 0
                or (not action.option_strings and action.nargs not in ("?", "*"))):
            return text
        return f"{text} (default: {_shown(action.default)})".replace("%", "%%")

    def _fill_text(self, text, width, indent):  # the description wraps, the epilog keeps its lines
        if "\n" in text:
            return super()._fill_text(text, width, indent)
        return argparse.HelpFormatter._fill_text(self, text, width, indent)


def _shown(value) -> str:
    """A default as typed on the command line: ``env_1 env_2``, ``runs``, ``none``."""
    if value is None or value == []:
        return "none"
    if isinstance(value, (list, tuple)):
        return " ".join(str(v) for v in value)
    return str(value)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cosim", description=DESCRIPTION, epilog=EXAMPLES,
                                formatter_class=HelpFormatter)
    p.add_argument("-v", "--verbose", action="store_true", help="log library messages (INFO)")
    sub = p.add_subparsers(metavar="COMMAND")

    s = sub.add_parser("scenarios", help="list the driving environments")
    s.set_defaults(func=sim.cmd_scenarios)

    d = sub.add_parser("drive", help="drive ACs with the scripted controller and print events")
    _scenario_args(d, steps=300)
    d.add_argument("--policy", choices=["autopilot", "random"], default="autopilot",
                   help="who drives the ACs: the scripted autopilot or uniform random actions")
    d.add_argument("--quiet", action="store_true", help="no progress bar")
    d.add_argument("--gui", action="store_true", help="watch it in sumo-gui (needs a display)")
    d.set_defaults(func=sim.cmd_drive)

    v = sub.add_parser("view", help="write camera mosaics and GIFs of what the ACs see")
    _scenario_args(v, steps=200)
    v.add_argument("--policy", choices=["autopilot", "random"], default="autopilot",
                   help="who drives the ACs: the scripted autopilot or uniform random actions")
    v.add_argument("--out", type=Path, default=Path("view"), help="output folder")
    v.add_argument("--image-size", type=int_in(8, 512), default=84, help="camera pixels (8-512)")
    v.add_argument("--moments", type=int_in(1), default=3, help="mosaics taken along the run")
    v.add_argument("--extent", type=float, default=100.0,
                   help="metres across the top-down view beside the mosaic")
    v.add_argument("--quiet", action="store_true", help="no progress bar")
    v.set_defaults(func=sim.cmd_view)

    n = sub.add_parser("nets", help="build or check the SUMO networks")
    n.add_argument("action", choices=["build", "check"],
                   help="build: run netconvert; check: fail if a built network is out of date")
    n.add_argument("--config", type=Path, action="append",
                   help="a netconvert .netccfg (default: every bundled network)")
    n.set_defaults(func=sim.cmd_nets)

    # the catalogue (no algorithm imported) and the environments (the scenario files)
    from agents.registry import ALGORITHMS, DETERMINISTIC, STOCHASTIC
    from eval.labels import ENVS
    from eval.training.options import add_flags
    from eval.training.runfolder import KEEP_POLICIES

    presets, preset_error = _preset_names()

    t = sub.add_parser("train", help="train N ACs of one algorithm together (or --algo all)")
    add_flags(t, "train", choices={"preset": presets})  # the run's options: eval/training/options.py
    t.add_argument("--out", type=Path, default=Path("runs"), help="folder for run folders")
    t.add_argument("--resume", type=Path, default=None, metavar="RUN_DIR",
                   help="continue an interrupted run from its last checkpoint (default: start a new run)")
    # how `--algo all` hands each of its runs its options (RunOptions.to_json); not for users
    t.add_argument("--options", default=None, metavar="JSON", help=argparse.SUPPRESS)
    t.add_argument("--pbt", type=int_in(2), default=None, metavar="P",
                   help="Population Based Training on Ray Tune with P trials (eval/scale/pbt.py)")
    t.add_argument("--pbt-interval", type=int_in(1), default=None, metavar="STEPS",
                   help="environment steps between PBT exploit/explore decisions (default: the "
                        "preset's checkpoint interval)")
    t.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="with --pbt: an existing Ray cluster, HOST:PORT (default: a local Ray)")
    t.add_argument("--keep", choices=sorted(KEEP_POLICIES), default="best",
                   help="what a finished run folder keeps: best = each AC's best.pt (the policy the "
                        "test drives), all = latest.pt too, to train it further (default: best)")
    t.add_argument("--quiet", action="store_true", help="plain log lines instead of a progress bar")
    t.set_defaults(func=_refuse(preset_error) if preset_error else learn.cmd_train)
    e = sub.add_parser("test", help="the test protocol: Scenario 1 (together) and 2 (alone), report")
    e.add_argument("--agents", type=int, default=6,
                   help=f"ACs in Scenario 1, one per algorithm in the order {' '.join(ALGORITHMS)}")
    e.add_argument("--algos", nargs="+", default=None, choices=list(ALGORITHMS), metavar="ALGO",
                   help="the algorithms tested, one AC each (default: the first --agents of that order)")
    e.add_argument("--envs", nargs="+", default=list(ENVS), metavar="ENV",
                   help=f"environments tested: {names_text(ENVS)} or scenario .yaml files")
    e.add_argument("--scenario", choices=["1", "2", "both"], default="both",
                   help="1: the ACs together in traffic; 2: each AC alone; both")
    e.add_argument("--episodes", type=int_in(1), default=3, help="episodes per environment and scenario")
    e.add_argument("--steps", type=int_in(1), default=None,
                   help="steps per episode (default: the scenario's horizon, 600 for the bundled environments)")
    e.add_argument("--seed", type=_seed, default=0, help="seed of the first episode (episode e: seed + e)")
    e.add_argument("--fixed-slots", action="store_true",
                   help="Scenario 1: algorithm i always drives ac_i (default: the algorithms take "
                        "turns at the spawn slots, one step per episode)")
    e.add_argument("--workers", type=int_in(1), default=1, metavar="N",
                   help="processes that run the test's episodes, one torch thread each (the "
                        "records are the same with any number; default 1)")
    e.add_argument("--greedy", action="store_true",
                   help=f"{', '.join(STOCHASTIC)} take their policy's mode (default: they sample "
                        f"it; {', '.join(DETERMINISTIC)} always act greedily)")
    e.add_argument("--policy", choices=["trained", "autopilot", "random"], default="trained",
                   help="trained checkpoints from --runs, or a reference driver")
    e.add_argument("--runs", type=Path, default=Path("runs"),
                   help="where `cosim train` wrote runs; each environment is tested with the newest "
                        "run of each algorithm trained in it")
    e.add_argument("--allow-cross-env", action="store_true",
                   help="test an environment with a checkpoint trained in another (warned) when "
                        "--runs has none trained in it, or with a --checkpoint from another; without "
                        "it such a test is refused")
    e.add_argument("--checkpoint", action="append", default=[], metavar="ALGO=PATH",
                   help="the checkpoint of one algorithm's AC in every slot and environment instead "
                        "of the newest under --runs (repeatable), e.g. --checkpoint "
                        "ppo=runs/x/checkpoints/ac_0/best.pt (default: none)")
    e.add_argument("--encoder", type=Path, default=None, metavar="FILE",
                   help="the frozen perception encoder of the checkpoints trained with --encoder (default: "
                        "the file each run recorded); a file with another sha256 than the run's is refused")
    e.add_argument("--out", type=Path, default=Path("reports"),
                   help="where reports go, each in a new <date>-<time> folder")
    e.add_argument("--references", default="all",
                   help="reference rows added to the report: 'all' (autopilot, random and the "
                        "degenerate suite of `cosim check-scenarios`), 'none', or a comma list")
    e.add_argument("--cross-play", action="store_true",
                   help="also the cross-play matrix: each algorithm's AC among ACs of each other "
                        "algorithm and among autopilots (eval/testing/robustness.py)")
    e.add_argument("--cross-play-group", type=int_in(2, 6), default=3, metavar="N",
                   help="ACs per cross-play episode: the ego and N-1 partners (default 3)")
    e.add_argument("--sweep", action="append", default=[], metavar="KIND=L1,L2",
                   help="also a robustness sweep (repeatable): density=0.5,1,2, camera_noise=0,0.05, "
                        "action_noise=0,0.2, dropout=0,0.3 (default: none)")
    e.add_argument("--no-replays", action="store_true",
                   help="skip the failure replays (clips and SUMO state of each first collision)")
    e.add_argument("--quiet", action="store_true", help="no progress bars")
    e.set_defaults(func=learn.cmd_test)

    _benchmark_parser(sub, presets, preset_error)
    encoder.add_parser(sub, HelpFormatter)  # cosim encoder train: eval/cli/encoder.py

    rp = sub.add_parser("replay", help="reopen a failure replay's SUMO state (from a cosim test report)")
    rp.add_argument("state", type=Path, help="replays/<...>/state.json (or state.xml) of a report")
    rp.add_argument("--plot", type=Path, default=None, metavar="PNG",
                    help="also draw the reloaded positions into this PNG (default: no plot)")
    rp.set_defaults(func=learn.cmd_replay)

    c = sub.add_parser("check-scenarios",
                       help="run the degenerate-policy suite: does a scenario measure driving?")
    c.add_argument("scenarios", nargs="*", default=list(ENVS),
                   help=f"{names_text(ENVS)} or scenario .yaml files (default: all of them)")
    c.add_argument("--agents", type=int, nargs="+", default=[3, 6], help="AC counts to check")
    c.add_argument("--episodes", type=int, default=5, help="held-out episodes per policy")
    c.add_argument("--steps", type=int, default=None, help="steps per episode (default: horizon)")
    c.add_argument("--out", type=Path, default=None,
                   help="also write the per-episode rows to this CSV (default: print only)")
    c.set_defaults(func=sim.cmd_check_scenarios)
    for command in sub.choices.values():
        command.formatter_class = HelpFormatter
    return p


def _preset_names():
    """The run presets' names (what ``--preset`` accepts) and None, or () and the
    :class:`~eval.training.presets.PresetError` of a preset YAML that does not load: then only the
    commands that read the presets fail, with that one-line error (:func:`_refuse`)."""
    from eval.training.presets import PresetError, preset_names

    try:
        return preset_names(), None
    except PresetError as exc:
        return (), exc


def _refuse(error: Exception):
    """A command function that raises ``error`` (a command that cannot run, e.g. without presets)."""
    def refuse(args):
        raise error

    return refuse


def _benchmark_parser(sub, presets: tuple[str, ...], preset_error: Exception | None) -> None:
    from agents.registry import ALGORITHMS
    from eval.labels import ENVS
    from eval.training.options import add_flags
    from eval.training.runfolder import KEEP_POLICIES

    trials = len(ENVS) * len(ALGORITHMS)
    b = sub.add_parser(
        "benchmark", help="train every (algorithm, environment, seed) as a Ray Tune trial, then test "
                          "them and write the report",
        description=f"Train every (algorithm, environment, seed) as a Ray Tune trial, test them "
                    f"(Scenario 1 and 2 in each environment) and write the report. Without options "
                    f"it runs the `standard` preset: {len(ALGORITHMS)} algorithms x {len(ENVS)} "
                    f"environments x 1 seed = {trials} trials, then the test with the whole reference "
                    "suite (how long each takes: docs/benchmarks.md). Start with --preset smoke (the "
                    "same grid with short trials: it checks the pipeline).")
    b.add_argument("--envs", nargs="+", default=list(ENVS), metavar="ENV",
                   help=f"environments of the grid: {names_text(ENVS)} or scenario .yaml files")
    b.add_argument("--algos", nargs="+", default=list(ALGORITHMS), metavar="ALGO",
                   help=f"algorithms of the grid: {' '.join(ALGORITHMS)}")
    b.add_argument("--seeds", type=int_in(1), default=1, metavar="K",
                   help="seeds 0..K-1 per (algorithm, environment), or from --first-seed")
    b.add_argument("--first-seed", type=_seed, default=0, metavar="S",
                   help="train seeds S..S+K-1 (default 0): a grid in parts, e.g. seed 1 alone; "
                        "each cell is the one a benchmark from seed 0 trains")
    # the run options every trial takes (those declared `benchmark` in eval/training/options.py)
    add_flags(b, "benchmark", choices={"preset": presets})
    b.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="an existing Ray cluster (HOST:PORT of `ray start --head`); default: local Ray")
    b.add_argument("--concurrent", type=int_in(1), default=None, metavar="N",
                   help="trials at once (default: the CPUs here, or unlimited on a cluster)")
    b.add_argument("--gpus-per-trial", type=float, default=0.0, metavar="F", help="GPU share of each trial (Ray resources)")
    b.add_argument("--no-ray", action="store_true",
                   help="train the same grid one trial after another in this process")
    b.add_argument("--train-only", action="store_true", help="train the grid, skip the test and report")
    b.add_argument("--keep", choices=sorted(KEEP_POLICIES), default="best",
                   help="what a finished trial's run folder keeps: best = each AC's best.pt, all = "
                        "latest.pt too (default: best)")
    b.add_argument("--out", type=Path, default=Path("benchmark"), help="benchmark folder")
    b.add_argument("--resume", action="store_true",
                   help="continue an interrupted benchmark in --out without redoing finished trials; "
                        "with a larger --seeds, add those seeds to a finished one")
    b.add_argument("--quiet", action="store_true", help="no progress lines")
    b.add_argument("--status", action="store_true",
                   help="print where the benchmark in --out stands (each trial's state, env steps, "
                        "best validation score, learning time left) and exit; starts nothing")
    b.set_defaults(func=_refuse(preset_error) if preset_error else learn.cmd_benchmark)


def _scenario_args(p: argparse.ArgumentParser, steps: int) -> None:
    from eval.labels import ENVS

    p.add_argument("scenario", nargs="?", default="env_3", help=f"{names_text(ENVS)} or a scenario .yaml")
    p.add_argument("--agents", type=int_in(1, 6), default=None,
                   help="learning cars (default: every spawn point of the scenario)")
    p.add_argument("--steps", type=int_in(1), default=steps, help="simulation steps")
    p.add_argument("--seed", type=_seed, default=0, help="seed of the episode (traffic, spawn order)")
    p.add_argument("--no-background", action="store_true", help="no background cars")
    p.add_argument("--no-pedestrians", action="store_true", help="no pedestrians")


def _seed(text: str) -> int:
    """An argparse type: a seed, a whole number 0..MAX_SEED (issue 57: -1 and 10^22 were
    unexpected errors from numpy and torch)."""
    return int_in(0, MAX_SEED)(text)

