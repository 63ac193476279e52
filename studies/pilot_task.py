"""Pilot learning runs of issue 25: the old task against the new one (and the new one with
``--obs nav``), PPO and DQN on Four-way (env_3) and Roundabout (env_4), one seed each.

    python studies/pilot_task.py --out pilot                   # 3 arms x 2 algos x 2 envs, quick
    python studies/pilot_task.py --out pilot                   # again after a kill: continues
    python studies/pilot_task.py --arms old new --jobs 2 --out pilot
    python studies/pilot_task.py --smoke --arms old new --out /tmp/pilot   # ~2 minutes, the CI check

Arms (docs/task.md), each with the same budget (``--preset``, ``--steps``):

- ``old``: the task before issue 25: the old steering (a copy of the scenario with
  ``vehicle: {discrete_steer_reference: 35, max_lateral_accel: null}``, written to
  ``OUT/scenarios/<env>_old.yaml``), ``--collisions end --frame-stack 1
  --validation-episodes 0``;
- ``new``: ``cosim train``'s defaults (70 degree discrete reference with the grip limit,
  collisions go on, 4 frames, best.pt by validation);
- ``nav``: the defaults with ``--obs nav`` (route command, speed and distance beside the
  image); refused in one line when ``cosim train`` has no ``--obs``;
- ``shared`` and ``nav-shared`` (not run unless named): ``new`` and ``nav`` with
  ``--share-params``, one network for the run's six ACs (agents/shared.py), which then learns
  from six times the transitions at the same environment steps and compute;
- ``nav-shared-r2`` (not run unless named): ``nav-shared`` with each action held for 2
  environment steps (``--set action_repeat=2``, docs/task.md "Action repeat");
- ``curriculum`` (not run unless named): ``nav-shared-r2`` trained first on Straight (env_1)
  for ``--pretrain-steps`` (default 40,000; one run per algorithm, ``OUT/runs/pretrain/``, not
  tested), then on each environment for the rest of ``--steps`` from its weights
  (``cosim train --init-from``, docs/agents.md "Warm start"): the same env steps per run as
  the other arms, the pretrain's counted in. A cell starts once its pretrain has finished;
- ``warm`` (not run unless named, with ``--init-from CKPT``): ``nav-shared-r2`` started from
  the weights of a checkpoint of that config (``cosim train --init-from``), e.g. the behaviour
  clone of the discrete autopilot that studies/bc_warmstart.py writes;
- ``route``, ``encoder``, ``encoder-route`` (the camera track's variants, not run unless named):
  ``new`` with ``--obs route`` (the AC's route drawn into its camera), with ``--encoder FILE``
  (heads on a frozen perception encoder), and with both (``--route-encoder FILE``, an encoder
  built with ``cosim encoder train --obs route``).

Every run is trained by a ``cosim train`` subprocess (``--jobs`` at once) into
``OUT/runs/<arm>/``, its output in ``OUT/logs/`` (``--keep all``: each AC's last checkpoint is
kept beside its best.pt, so another selection can be tested without training again). A rerun of the same command skips finished
runs, resumes unfinished ones (``cosim train --resume``: a kill loses at most one checkpoint
interval) and skips finished tests; the plan (preset, steps, seed, test) is kept in
``OUT/plan.json`` and a rerun with another is refused.

Test: each run's ACs drive together, each in the slot it was trained in with its own selected
checkpoint (eval/testing/checkpoints.py ``slot_checkpoint``: best.pt, chosen by the run's own rule), under
the test's rules (collisions go on, every contact step charged, the scenario's horizon, PPO
sampling and DQN greedy), on the held-out episode seeds 10,000, 10,001, ...
(eval.testing.validity.HELD_OUT_SEED), with background traffic, in the new task's environment except
the steering, which follows the arm: a car trained with the old wheel drives with the old wheel.
References on the same seeds, AC count and steps (eval/testing/validity.py ``run_policy``):
always-brake, safe-non-turner, autopilot-discrete and autopilot on the new task's car, and
autopilot-discrete on the old wheel when the old arm runs.

Output in OUT: ``results.csv`` (one row per arm x algorithm x environment x slot, and per
reference x environment x slot: mean return, goal rate and contact steps per AC-episode, the
slot's movement and whether its route turns), ``summary.md`` (per environment a table of mean
return, goal rate over all slots, over turning slots and per slot, contact steps, whether the
return clears always-brake and whether a turning slot reaches goals; and the issue's target),
the test records ``test/<arm>__<env>__<algo>.parquet`` and the reference rows
``references/<env>__<car>.csv``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for path in (ROOT, ROOT / "studies"):  # run as a script from a checkout; studies/science.py
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import yaml  # noqa: E402
from science import _write  # noqa: E402

from cosim.errors import CosimError  # noqa: E402
from cosim.scenario import load_scenario, scenario_data, scenario_file  # noqa: E402
from eval.testing.validity import HELD_OUT_SEED  # noqa: E402

ARMS = ("old", "new", "nav", "shared", "nav-shared", "nav-shared-r2", "curriculum", "warm",
        "state", "state-both", "state-step", "state-end", "state-utd2", "route", "encoder",
        "encoder-route")
DEFAULT_ARMS = ("old", "new", "nav")
"""The arms the issue asks for; ``shared`` and ``nav-shared`` are the parameter-sharing variants."""
OLD_VEHICLE = {"discrete_steer_reference": 35, "max_lateral_accel": None}
"""The steering before issue 25 as a scenario ``vehicle:`` block (docs/guide.md)."""
R2_FLAGS = ["--obs", "nav", "--share-params", "--set", "action_repeat=2"]
"""nav-shared-r2's flags, which the curriculum's two stages and the warm arm train with too."""
ARM_FLAGS = {
    "old": ["--collisions", "end", "--frame-stack", "1", "--validation-episodes", "0"],
    "new": [],
    "nav": ["--obs", "nav"],
    "shared": ["--share-params"],
    "nav-shared": ["--obs", "nav", "--share-params"],
    "nav-shared-r2": R2_FLAGS,
    "curriculum": R2_FLAGS,
    "warm": R2_FLAGS,
    "pretrain": R2_FLAGS,  # the curriculum's first stage (pretrain_cell), not an arm of its own
    # the state track (issue 61): the default collision rule (task version 5: charged once per
    # event, to the car at fault) and the ones it replaced (both cars charged: version 4)
    "state": ["--obs", "state"],
    "state-both": ["--obs", "state", "--fault", "both"],
    "state-step": ["--obs", "state", "--collisions", "step"],
    "state-end": ["--obs", "state", "--collisions", "end"],
    # DQN/DDPG/TD3 with a gradient step per 2 of each AC's transitions, not the standard preset's 8,
    # which was chosen for the CNN's cost (docs/benchmarks.md "Update-to-data ratio")
    "state-utd2": ["--obs", "state", "--set", "train_freq=2"],
    # the camera track's variants (docs/task.md, "The route variant", "The frozen perception
    # encoder"): ``new`` is the camera as it is; the encoder arms add ``--encoder`` (below)
    "route": ["--obs", "route"],
    "encoder": [],
    "encoder-route": ["--obs", "route"],
}
ENCODER_ARMS = {"encoder": "encoder", "encoder-route": "route_encoder"}
"""The arms that learn heads on a frozen encoder, and the option naming its file: an encoder
takes the camera variant it was built on (`cosim encoder train --obs route` for encoder-route)."""
SCENARIO_ARMS = {"old": ("_old", {"vehicle": OLD_VEHICLE})}
"""Arms that train on a copy of the scenario: the copy's name suffix and the keys it changes
(the old arm is tested on its copy: its car)."""
PRETRAIN_ENV = "env_1"
"""Where the curriculum arm learns to drive first: Straight, no turn (the quick PPO reached 0.94
of its goals there)."""
PRETRAIN_STEPS = 40_000
REFERENCES = ("always-brake", "safe-non-turner", "autopilot-discrete", "autopilot")
OLD_REFERENCES = ("autopilot-discrete",)
"""References also driven with the old wheel when the old arm runs (the old arm's ceiling)."""
SMOKE = {"preset": "smoke", "envs": ["env_4"], "algos": ["ppo", "dqn"], "steps": 40,
         "episodes": 1, "test_steps": 40}
PLAN_KEYS = ("preset", "steps", "seed", "episodes", "test_steps", "pretrain_steps", "init_from", "encoder",
             "route_encoder")


class PilotError(CosimError, ValueError):
    """The study cannot run as asked; the message says what to change."""


def say(msg: str) -> None:
    print(f"[pilot] {msg}", file=sys.stderr, flush=True)


def smoke_defaults(args: argparse.Namespace, smoke: dict) -> argparse.Namespace:
    """With ``--smoke``, the ``smoke`` values for the options the command did not give."""
    if args.smoke:
        for key, value in smoke.items():
            if getattr(args, key) is None:
                setattr(args, key, value)
    return args


def parse(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("pilot_task"), help="study folder")
    p.add_argument("--arms", nargs="+", choices=ARMS, default=list(DEFAULT_ARMS),
                   help=f"default: {' '.join(DEFAULT_ARMS)}")
    p.add_argument("--algos", nargs="+", default=None, help="default: ppo dqn")
    p.add_argument("--envs", nargs="+", default=None, help="default: env_3 env_4")
    p.add_argument("--seed", type=int, default=0, help="training seed of every run")
    p.add_argument("--preset", default=None, help="training budget (default: quick)")
    p.add_argument("--steps", type=int, default=None,
                   help="environment steps per run, every arm alike (default: the preset's)")
    p.add_argument("--episodes", type=int, default=None, help="test episodes per run (default 5)")
    p.add_argument("--test-steps", type=int, default=None,
                   help="steps per test episode (default: the scenario's horizon)")
    p.add_argument("--pretrain-steps", type=int, default=None,
                   help=f"the curriculum arm's env steps on {PRETRAIN_ENV}, part of --steps "
                        f"(default {PRETRAIN_STEPS:,})")
    p.add_argument("--init-from", default=None, metavar="CKPT",
                   help="the warm arm's starting weights (a PPO or DQN checkpoint of nav-shared-r2's config)")
    p.add_argument("--encoder", default=None, metavar="FILE",
                   help="the encoder arm's frozen encoder (`cosim encoder train --out FILE`)")
    p.add_argument("--route-encoder", default=None, metavar="FILE",
                   help="the encoder-route arm's (`cosim encoder train --obs route --out FILE`)")
    p.add_argument("--jobs", type=int, default=1, help="training runs at once (default 1)")
    p.add_argument("--keep", choices=("best", "all"), default="best",
                   help="what a finished run keeps (`cosim train --keep`): all keeps each AC's last "
                        "checkpoint beside best.pt, to test another selection later (default: best)")
    p.add_argument("--smoke", action="store_true",
                   help="the CI check: --preset smoke --envs env_4 --algos ppo dqn --steps 40 "
                        "--episodes 1 --test-steps 40 (options given explicitly win)")
    args = smoke_defaults(p.parse_args(argv), SMOKE)
    args.preset = args.preset or "quick"
    args.algos = args.algos or ["ppo", "dqn"]
    args.envs = args.envs or ["env_3", "env_4"]
    args.episodes = args.episodes or 5
    if args.jobs < 1 or args.episodes < 1 or (args.steps is not None and args.steps < 1) or (
            args.test_steps is not None and args.test_steps < 1):
        p.error("--jobs, --episodes, --steps and --test-steps must be >= 1")
    if "curriculum" in args.arms:
        budget = args.steps
        if budget is None:
            from eval.training.presets import load_presets

            budget = max(load_presets()[args.preset].steps[a] for a in args.algos)
        args.pretrain_steps = args.pretrain_steps or min(PRETRAIN_STEPS, budget // 2)
        if not 1 <= args.pretrain_steps < budget:
            p.error(f"--pretrain-steps must be 1..{budget - 1} (below the run's --steps {budget})")
    if ("warm" in args.arms) != (args.init_from is not None):
        p.error("the warm arm and --init-from CKPT go together")
    if args.init_from is not None:
        args.init_from = str(Path(args.init_from).resolve())
    for arm, key in ENCODER_ARMS.items():
        flag = "--" + key.replace("_", "-")
        if (arm in args.arms) != (getattr(args, key) is not None):
            p.error(f"the {arm} arm and {flag} FILE go together")
        if getattr(args, key) is not None:
            if not Path(getattr(args, key)).is_file():
                p.error(f"{flag} {getattr(args, key)}: no such file; build one with `cosim encoder train`")
            setattr(args, key, str(Path(getattr(args, key)).resolve()))
    args.out = args.out.resolve()
    return args


# -- the plan ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Cell:
    arm: str
    env: str
    algo: str

    @property
    def name(self) -> str:
        return f"{self.arm}__{self.env}__{self.algo}"


def cells(args) -> list[Cell]:
    """The tested cells, arm x environment x algorithm (a curriculum's pretrain is not one)."""
    return [Cell(arm, env, algo) for arm in args.arms for env in args.envs for algo in args.algos]


def pretrain_cell(algo: str) -> Cell:
    """The curriculum arm's first stage for ``algo``: nav-shared-r2 on Straight."""
    return Cell("pretrain", PRETRAIN_ENV, algo)


def depends_on(cell: Cell) -> Cell | None:
    """The cell that must finish before ``cell`` starts (a curriculum cell's pretrain)."""
    return pretrain_cell(cell.algo) if cell.arm == "curriculum" else None


def cell_steps(cell: Cell, args) -> int | None:
    """Env steps of a cell's own run: a curriculum cell's budget less its pretrain's."""
    if cell.arm == "pretrain":
        return args.pretrain_steps
    if cell.arm == "curriculum":
        return _budget(cell, args) - args.pretrain_steps
    return args.steps


def _budget(cell: Cell, args) -> int:
    if args.steps is not None:
        return args.steps
    from eval.training.presets import load_presets

    return load_presets()[args.preset].steps[cell.algo]


def check_plan(out: Path, args) -> None:
    """plan.json: what a rerun must repeat (arms, algorithms and environments may change)."""
    plan = {k: getattr(args, k) for k in PLAN_KEYS}
    saved = out / "plan.json"
    if saved.exists():
        old = json.loads(saved.read_text())
        if {k: old.get(k) for k in PLAN_KEYS} != plan:
            diff = ", ".join(f"--{k.replace('_', '-')} {old.get(k)}" for k in PLAN_KEYS
                             if old.get(k) != plan[k])
            raise PilotError(f"{out} holds a study started with {diff}; repeat those options or "
                             "choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    saved.write_text(json.dumps(plan, indent=2))


def old_scenario(out: Path, env: str, arm: str = "old") -> Path:
    """``OUT/scenarios/<env><suffix>.yaml``: the bundled scenario with an arm's changes
    (:data:`SCENARIO_ARMS`; the old arm's: the old steering). Its file paths are made absolute
    (the copy lives elsewhere than the bundled YAML it comes from)."""
    suffix, changes = SCENARIO_ARMS[arm]
    src = scenario_file(env)
    data = scenario_data(src)
    clash = sorted(set(changes) & set(data))
    if clash:
        raise PilotError(f"{src} has a {clash[0]}: block of its own; the {arm} arm replaces it")
    data.update(changes)
    path = out / "scenarios" / f"{Path(env).stem}{suffix}.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    text = (f"# {src.name} with {changes} (studies/pilot_task.py, {arm} arm)\n"
            + yaml.safe_dump(data, sort_keys=False))
    if not path.exists() or path.read_text() != text:
        path.write_text(text)
    load_scenario(path)  # refuses here, not in a training subprocess
    return path


def env_arg(out: Path, cell: Cell) -> str:
    """What ``cosim train --env`` gets: the old arm's scenario file, else the environment."""
    return str(old_scenario(out, cell.env, cell.arm)) if cell.arm in SCENARIO_ARMS else cell.env


# -- training ----------------------------------------------------------------------------------
def find_run(out: Path, cell: Cell, seed: int) -> Path | None:
    """The cell's run folder under ``OUT/runs/<arm>``: the newest if there are several."""
    stem = Path(cell.env).stem + (SCENARIO_ARMS[cell.arm][0] if cell.arm in SCENARIO_ARMS else "")
    found = sorted((out / "runs" / cell.arm).glob(f"{stem}__{cell.algo}__{seed}__*"))
    found = [p for p in found if (p / "config.yaml").exists()]
    return found[-1] if found else None


def run_status(run: Path | None, steps: int | None = None) -> str:
    """``missing`` (no run folder), ``unfinished`` or ``finished`` (its steps all done: its own
    budget, or ``steps`` when that is larger: a run trained further, see :func:`train_command`)."""
    from eval.training.runfolder import load_run_config, read_state

    if run is None:
        return "missing"
    state = read_state(run)
    budget = max(load_run_config(run).steps, steps or 0)
    done = state is not None and int(state["env_steps"]) >= budget
    return "finished" if done else "unfinished"


def train_command(out: Path, cell: Cell, args, run: Path | None) -> list[str]:
    """``cosim train`` for a cell: ``--resume RUN`` when it has a run folder (with ``--steps``
    when the plan's budget is larger than the run's: a run copied in from a shorter study with
    its latest.pt trains on, ``cosim train --resume RUN --steps N``), else a new run."""
    from eval.training.runfolder import load_run_config

    base = [sys.executable, "-m", "eval.cli", "train"]
    keep = ["--keep", "all"] if args.keep == "all" else []
    if run is not None:
        steps = cell_steps(cell, args)
        more = steps is not None and load_run_config(run).steps < steps
        return [*base, "--resume", str(run), *keep, "--quiet", *(["--steps", str(steps)] if more else [])]
    cmd = [*base, "--algo", cell.algo, "--env", env_arg(out, cell), "--preset", args.preset,
           "--seed", str(args.seed), "--out", str(out / "runs" / cell.arm), "--quiet", *keep]
    if cell_steps(cell, args) is not None:
        cmd += ["--steps", str(cell_steps(cell, args))]
    source = depends_on(cell)
    if source is not None:
        found = find_run(out, source, args.seed)
        if found is None:
            raise PilotError(f"{cell.name} starts from {source.name}, which has no run yet")
        cmd += ["--init-from", str(found)]
    if cell.arm == "warm":
        cmd += ["--init-from", args.init_from]
    if cell.arm in ENCODER_ARMS:
        cmd += ["--encoder", getattr(args, ENCODER_ARMS[cell.arm])]
    return cmd + ARM_FLAGS[cell.arm]


def check_obs_flag(help_text: str) -> None:
    """The nav arm needs ``cosim train --obs``; refuse in one line when it is not there."""
    if "--obs" not in help_text:
        raise PilotError("the nav arm needs `cosim train --obs nav`, which this checkout's "
                         "`cosim train` does not accept; run --arms old new, or update cosim")


def _train_help() -> str:
    done = subprocess.run([sys.executable, "-m", "eval.cli", "train", "--help"], cwd=ROOT,
                          env=_child_env(), capture_output=True, text=True, timeout=300)
    return done.stdout + done.stderr


def _child_env() -> dict[str, str]:
    """This checkout first on the children's path (the installed cosim may be another's), and
    the pid they die with: a `cosim train` child stops resumably (SIGTERM) when this driver
    dies, even by kill -9 (eval/cli/learn.py OWNER_ENV, as `--algo all`'s children do)."""
    from eval.cli.learn import OWNER_ENV

    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *filter(None, [env.get("PYTHONPATH")])])
    env[OWNER_ENV] = str(os.getpid())
    return env


# -- test and references -----------------------------------------------------------------------
def test_steps(args, env: str) -> int:
    return args.test_steps or load_scenario(env).horizon


def test_run(run: Path, algo: str, episodes: int, steps: int, env: str | None = None) -> pd.DataFrame:
    """The run's ACs together, each in its own slot with its own selected checkpoint, under
    the test's rules, in the run's scenario (its car) or ``env``, on the held-out seeds."""
    from eval.testing import selection
    from eval.testing.protocol import ProtocolPlan
    from eval.testing.session import TestRequest, run_test
    from eval.training.runfolder import load_run_config

    cfg = load_run_config(run)
    chosen = selection.choose(run)
    if chosen is None:
        raise PilotError(f"{run} has no checkpoint")
    plan = ProtocolPlan(envs=(env or cfg.env,), scenarios=(1,), episodes=episodes, steps=steps,
                        seed=HELD_OUT_SEED, agents=cfg.agents, rotate=False)
    records = run_test(TestRequest(plan, (algo,) * cfg.agents,
                                   checkpoints={plan.envs[0]: {algo: chosen.path}})).records
    slots = sorted(set(records["agent"]))
    paths = {s: selection.checkpoint_of(run, s) for s in slots}
    return records.assign(checkpoint=records["agent"].map(
        {s: str(p.relative_to(run.parent)) if p else "" for s, p in paths.items()}),
        selection_basis=chosen.basis)


def references(out: Path, env: str, car: str, policies, agents: int, episodes: int,
               steps: int) -> pd.DataFrame:
    """Reference rows (eval/testing/validity.py run_policy), cached as references/<env>__<car>.csv."""
    from eval.testing import validity

    path = out / "references" / f"{env}__{car}.csv"
    if path.exists():
        return pd.read_csv(path)
    start = time.monotonic()
    sc = load_scenario(old_scenario(out, env) if car == "old" else env)
    rows = pd.concat([validity.run_policy(sc, p, agents, episodes, steps) for p in policies],
                     ignore_index=True).assign(env=env, car=car)
    _write(rows, path)
    say(f"references {env} ({car} car): {', '.join(policies)} ({time.monotonic() - start:.0f} s)")
    return rows


# -- results -----------------------------------------------------------------------------------
def slot_routes(env: str) -> pd.DataFrame:
    """Per slot of ``env``: its route's movement and whether it turns
    (eval.reporting.multiseed.slot_routes, which the 6x5 study's turning-slot goal rate uses)."""
    from eval.reporting.multiseed import slot_routes as routes

    return routes(env)


def per_slot(records: pd.DataFrame) -> pd.DataFrame:
    """Test records -> one row per (episode, slot): return, goal, contact steps (and the
    checkpoint that drove the slot, when the records say)."""
    from eval.testing.metrics import score_of

    g = records.groupby(["episode", "agent"])
    out = pd.DataFrame({"return": g["reward"].sum(), "goal": g["goal_reached"].any().astype(float),
                        "contact_steps": g["collision"].sum().astype(float)})
    scores = pd.DataFrame({k: score_of(e.sort_values("step")) for k, e in g}).T
    out["DS"], out["RC"] = scores["DS"].astype(float), scores["RC"].astype(float)
    out["events"] = scores[["CV_events", "CO_events", "CP_events"]].astype(float).sum(axis=1, min_count=1)
    if "checkpoint" in records:
        out["checkpoint"] = g["checkpoint"].first()
    return out.reset_index().rename(columns={"agent": "slot"})


def slot_table(episodes: pd.DataFrame, routes: pd.DataFrame, **labels) -> pd.DataFrame:
    """(episode, slot) rows -> one row per slot: means over episodes, with its route."""
    for c in SCORE_COLS:  # reference rows of validity.run_policy name them as the records do
        if c not in episodes:
            episodes = episodes.assign(**{c: np.nan})
    t = episodes.groupby("slot").agg(episodes=("return", "size"), **{
        c: (c, "mean") for c in ("return", "goal", "contact_steps", *SCORE_COLS)}).reset_index()
    if "checkpoint" in episodes:
        t["checkpoint"] = episodes.groupby("slot")["checkpoint"].first().to_numpy()
    t = t.merge(routes, on="slot", how="left")
    return t.assign(**labels).reindex(columns=[*labels, "slot", "movement", "turning", "episodes",
                                               "return", "goal", "contact_steps", *SCORE_COLS,
                                               "checkpoint"])


SCORE_COLS = ("DS", "RC", "events")
"""Per (episode, slot): driving score, route completion, collision events (task versions 4-5)."""


def results(out: Path, args) -> pd.DataFrame:
    """results.csv: every tested cell and every reference, one row per slot."""
    parts = []
    for env in args.envs:
        routes = slot_routes(env)
        for cell in (c for c in cells(args) if c.env == env):
            path = out / "test" / f"{cell.name}.parquet"
            if path.exists():
                parts.append(slot_table(per_slot(pd.read_parquet(path)), routes, env=env,
                                        arm=cell.arm, algo=cell.algo, car=_car(cell.arm),
                                        row=f"{cell.arm} {cell.algo}"))
        for path in sorted((out / "references").glob(f"{env}__*.csv")):
            refs = pd.read_csv(path).rename(columns={"agent": "slot", "collision_steps": "contact_steps",
                                                     "collision_events": "events"})
            car = path.stem.split("__")[1]
            for policy, g in refs.groupby("policy", sort=False):
                row = f"ref: {policy}" + (" (old wheel)" if car == "old" else "")
                parts.append(slot_table(g, routes, env=env, arm="reference", algo=policy,
                                        car=car, row=row))
    table = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()
    if not table.empty:
        _write(table, out / "results.csv")
    return table


def _car(arm: str) -> str:
    """The car an arm trains and is tested with: the old wheel for the old arm."""
    return "old" if arm == "old" else "new"


def _fmt(v: float, digits: int = 2) -> str:
    return "-" if v is None or (isinstance(v, float) and np.isnan(v)) else f"{v:.{digits}f}"


def env_summary(table: pd.DataFrame, env: str) -> tuple[str, list[str]]:
    """The markdown table of one environment and the rows of the new task that meet the target
    (return above always-brake's and a turning slot with goals)."""
    t = table[table["env"] == env]
    slots = t.drop_duplicates("slot").sort_values("slot")
    brake = t[t["row"] == "ref: always-brake"]
    brake_return = float(brake["return"].mean()) if len(brake) else np.nan
    safe = t[t["row"] == "ref: safe-non-turner"]
    safe_ds = float(safe["DS"].mean()) if len(safe) and "DS" in safe else np.nan
    head = ["row", "return / AC-episode", "goal rate", "goal rate, turning slots",
            *[f"{s} {m}{'*' if turn else ''}" for s, m, turn in
              zip(slots["slot"], slots["movement"], slots["turning"], strict=True)],
            "contact steps / AC-episode", "clears always-brake", "a turning slot reaches goals",
            "driving score", "RC, turning slots", "collision events / AC-episode",
            "every turning slot >= 0.5 goals", "DS above safe-non-turner"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    met = []
    order = list(dict.fromkeys(t["row"]))
    for row in order:
        g = t[t["row"] == row].set_index("slot")
        turning = g[g["turning"].astype(bool)]
        ret = float((g["return"] * g["episodes"]).sum() / g["episodes"].sum())
        clears = "-" if row == "ref: always-brake" or np.isnan(brake_return) else (
            "yes" if ret > brake_return else "no")
        reached = [s for s in turning.index if turning.loc[s, "goal"] > 0]
        turn_goal = "-" if turning.empty else (f"yes ({', '.join(reached)})" if reached else "no")
        ds = float(g["DS"].mean()) if "DS" in g else np.nan
        every_turn = "-" if turning.empty else ("yes" if (turning["goal"] >= 0.5).all() else "no")
        above_safe = "-" if row == "ref: safe-non-turner" or np.isnan(safe_ds) or np.isnan(ds) else (
            "yes" if ds > safe_ds else "no")
        cells_ = [row, _fmt(ret, 1), _fmt(float(g["goal"].mean())),
                  _fmt(float(turning["goal"].mean()) if len(turning) else np.nan),
                  *[_fmt(float(g.loc[s, "goal"])) if s in g.index else "-" for s in slots["slot"]],
                  _fmt(float(g["contact_steps"].mean()), 1), clears, turn_goal,
                  _fmt(ds), _fmt(float(turning["RC"].mean()) if len(turning) and "RC" in turning else np.nan),
                  _fmt(float(g["events"].mean()) if "events" in g else np.nan), every_turn, above_safe]
        lines.append("| " + " | ".join(cells_) + " |")
        if row.startswith("state"):  # issue 61's target for the state track
            if every_turn == "yes" and above_safe == "yes":
                met.append(row)
        elif not row.startswith("ref:") and clears == "yes" and reached:
            met.append(row)
    return "\n".join(lines), met


def summary(table: pd.DataFrame, args) -> str:
    from eval.reporting.report import env_title

    parts = [f"Preset `{args.preset}`" + (f", {args.steps} steps per run" if args.steps else "")
             + f", training seed {args.seed}; test: {args.episodes} held-out episodes (seeds "
             f"{HELD_OUT_SEED}..), collisions go on. Per-slot columns are goal rates, the slot's "
             "route movement beside it (* = the route turns). Rows `old`, `new`, `nav` are the "
             "arms; `ref:` rows the scripted references, on the new task's car unless `(old "
             "wheel)`.\n"]
    met_by: dict[str, set[str]] = {}
    for env in args.envs:
        if table.empty or env not in set(table["env"]):
            parts.append(f"\n## {env_title(env)} ({env})\n\nnothing tested yet\n")
            continue
        md, met = env_summary(table, env)
        parts.append(f"\n## {env_title(env)} ({env})\n\n{md}\n")
        for row in met:
            met_by.setdefault(row, set()).add(env)
    parts.append("\n## Target\n\nIssue 25's arms (old, new, nav, ...): on the new task the test "
                 "return clears always-brake and a turning slot reaches goals. Issue 61's state "
                 "arms: every turning slot reaches >= 0.5 goals on the held-out test and the "
                 "six-AC driving score is above the safe non-turner's. In each environment, for "
                 "at least one algorithm:\n")
    for arm in (a for a in args.arms if a != "old"):
        full = [r.split(" ", 1)[1] for r, envs in met_by.items()
                if r.startswith(f"{arm} ") and envs >= set(args.envs)]
        some = {r: sorted(envs) for r, envs in met_by.items() if r.startswith(f"{arm} ")}
        verdict = (f"**met** by {', '.join(full)}" if full else
                   "**not met**" + (f" (met in {some})" if some else ""))
        parts.append(f"- `{arm}` arm: {verdict}")
    return "\n".join(parts) + "\n"


# -- the loop ----------------------------------------------------------------------------------
def plan_work(out: Path, args) -> tuple[list[Cell], list[Cell]]:
    """(cells to train or resume, a curriculum's pretrains first; cells trained but not tested)."""
    to_train, to_test = [], []
    pretrains = list(dict.fromkeys(depends_on(c) for c in cells(args) if depends_on(c)))
    for cell in pretrains:
        if run_status(find_run(out, cell, args.seed), cell_steps(cell, args)) != "finished":
            to_train.append(cell)
    for cell in cells(args):
        status = run_status(find_run(out, cell, args.seed), cell_steps(cell, args))
        if status != "finished":
            to_train.append(cell)
        elif not (out / "test" / f"{cell.name}.parquet").exists():
            to_test.append(cell)
    return to_train, to_test


def run_test(out: Path, cell: Cell, args) -> bool:
    run = find_run(out, cell, args.seed)
    start = time.monotonic()
    try:
        records = test_run(run, cell.algo, args.episodes, test_steps(args, cell.env))
    except Exception as exc:  # noqa: BLE001 - one failed test must not stop the others
        say(f"test {cell.name}: FAILED ({type(exc).__name__}: {exc}); rerun to retry")
        return False
    _write(records.assign(arm=cell.arm, env=cell.env), out / "test" / f"{cell.name}.parquet")
    s = per_slot(records)
    say(f"test {cell.name}: return {s['return'].mean():.1f}, goal rate {s['goal'].mean():.2f}, "
        f"contact steps {s['contact_steps'].mean():.1f} per AC-episode "
        f"({time.monotonic() - start:.0f} s)")
    return True


def startable(out: Path, cell: Cell, args) -> bool:
    """Whether ``cell`` can start now: it depends on nothing, or its pretrain has finished."""
    source = depends_on(cell)
    return source is None or run_status(find_run(out, source, args.seed), cell_steps(source, args)) == "finished"


def start_ready(out: Path, to_train: list[Cell], running: list, failed: list[str], args) -> None:
    """Start cells of ``to_train`` whose pretrain has finished, up to ``--jobs`` running; when
    none runs and none can start (their pretrain failed), list them as failed."""
    while len(running) < args.jobs:
        ready = [c for c in to_train if startable(out, c, args)]
        if not ready:
            break
        to_train.remove(ready[0])
        running.append(start_training(out, ready[0], args))
    if to_train and not running:
        for cell in to_train:
            say(f"train {cell.name}: not started, {depends_on(cell).name} did not finish")
            failed.append(cell.name)
        to_train.clear()


def start_training(out: Path, cell: Cell, args) -> subprocess.Popen:
    run = find_run(out, cell, args.seed)
    cmd = train_command(out, cell, args, run)
    log = out / "logs" / f"{cell.name}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("a") as fh:
        fh.write(f"\n$ {' '.join(cmd)}\n")
        fh.flush()
        proc = subprocess.Popen(cmd, cwd=ROOT, env=_child_env(), stdout=fh, stderr=subprocess.STDOUT)
    say(f"train {cell.name}: {'resumed ' + run.name if run else 'started'} (pid {proc.pid}, log {log})")
    proc.cell, proc.started = cell, time.monotonic()  # type: ignore[attr-defined]
    return proc


def main(argv=None) -> int:
    args = parse(argv)
    out = args.out
    try:
        check_plan(out, args)
        to_train, to_test = plan_work(out, args)
        if any(c.arm.startswith("nav") for c in to_train):
            check_obs_flag(_train_help())
        for cell in cells(args):
            env_arg(out, cell)  # old scenarios written and checked before anything runs
    except (CosimError, OSError) as exc:
        print(f"pilot_task: error: {exc}", file=sys.stderr)
        return 2
    agents = _agents(args)
    _acting_threads()
    chores = [("references", env) for env in args.envs]  # run in this process between polls
    chores += [("test", c) for c in to_test]
    say(f"{len(cells(args))} runs: {len(to_train)} to train, {len(to_test)} to test "
        f"(jobs {args.jobs}) -> {out}")
    running: list[subprocess.Popen] = []
    failed: list[str] = []
    try:
        while to_train or running or chores:
            for proc in [p for p in running if p.poll() is not None]:
                running.remove(proc)
                cell = proc.cell  # type: ignore[attr-defined]
                mins = (time.monotonic() - proc.started) / 60  # type: ignore[attr-defined]
                done = run_status(find_run(out, cell, args.seed), cell_steps(cell, args)) == "finished"
                if proc.returncode == 0 and done:
                    say(f"train {cell.name}: finished ({mins:.1f} min)")
                    if cell.arm != "pretrain":
                        chores.append(("test", cell))
                else:
                    say(f"train {cell.name}: FAILED (exit {proc.returncode}, {mins:.1f} min); see "
                        f"{out / 'logs' / (cell.name + '.log')}; rerun to resume")
                    failed.append(cell.name)
            start_ready(out, to_train, running, failed, args)  # before a chore: it takes minutes
            if chores:
                kind, what = chores.pop(0)
                if kind == "references":
                    _references(out, what, args, agents)
                elif not run_test(out, what, args):
                    failed.append(what.name)
            elif running:
                time.sleep(2.0)
    finally:
        for proc in running:  # interrupted: the runs resume at their last checkpoint
            proc.terminate()
    table = results(out, args)
    text = summary(table, args)
    (out / "summary.md").write_text(text)
    print(text)
    if failed:
        say(f"not finished: {', '.join(failed)}; rerun the same command to continue")
    return 1 if failed else 0


def _acting_threads() -> None:
    """One torch thread in this process, which only acts (the tests): two OpenMP threads on
    a busy 2-core machine made a forward pass ~20x slower (docs/benchmarks.md, "Where PPO's
    CPU goes"); here a 60-step test of 6 PPO ACs took 62 s with 2 threads, 14 s with 1."""
    import torch

    torch.set_num_threads(1)


def _agents(args) -> int:
    from eval.training.presets import load_presets

    return load_presets()[args.preset].agents


def _references(out: Path, env: str, args, agents: int) -> None:
    steps = test_steps(args, env)
    references(out, env, "new", REFERENCES, agents, args.episodes, steps)
    if "old" in args.arms:
        references(out, env, "old", OLD_REFERENCES, agents, args.episodes, steps)


if __name__ == "__main__":
    sys.exit(main())
