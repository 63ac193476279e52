"""The science study (issue 14): every algorithm x environment x seed trained with
`cosim benchmark`, tested on held-out episode seeds (collisions do not end an episode)
beside the reference rows, with confidence intervals over seeds.

    python studies/science.py                      # 6 algorithms x 5 environments x 3 seeds
    python studies/science.py --smoke --out /tmp/s # the CI version: env_1, PPO + DQN, 2 seeds
    python studies/science.py --envs env_2 env_3 --seeds 1 --out s23   # a part of the grid
    python studies/science.py --combine s1 s23 s45 --out all             # one table over the parts
    python studies/science.py --envs env_5 --seeds 1 --runs b1 b2 --out s5  # runs trained elsewhere

Stages, each resumable (rerun the same command after an interruption). A finished study
takes more seeds by rerunning it with a larger ``--seeds`` (nothing else changed): its runs
and test records stay, only the new seeds are trained (or linked with ``--runs``) and tested.

1. training: ``cosim benchmark --train-only`` into ``OUT/bench`` (``--resume`` when that
   folder holds a benchmark; skipped when every run is finished); with ``--runs`` the
   finished runs of other ``cosim benchmark --train-only`` folders (say two processes of
   three algorithms each, one per core) are linked in instead, once their configs are
   checked against the plan's;
2. test: per (environment, training seed) one test session (eval/testing/session.py) with that
   seed's checkpoints on episode seeds from eval.testing.validity.HELD_OUT_SEED (10,000; training
   uses small seeds), saved as ``OUT/test/<env>__seed<k>.parquet``;
3. references: the autopilot, uniform random and degenerate suite (eval/testing/validity.py) on the
   same episode seeds, AC count and steps, saved as ``OUT/references/<env>.csv``;
4. results (eval/reporting/multiseed.py, studies/science_pages.py): ``results.csv``/``results.md`` (mean and 95% bootstrap CI over
   seeds of every metric, reference rows beside), ``verdict.csv``/``verdict.md``/``verdict.png``,
   ``iqm.csv``/``iqm.md``/``iqm.png``, ``convergence.pdf``/``.png`` (+ ``convergence.csv``), ``budget.csv``
   (did each run's training return still rise at the end of its budget?),
   ``summary.md`` (printed: a study's results section, for its docs/results/<date>-<study>/ page), ``report/`` (the `cosim test`
   report of the held-out records, seeds pooled) and ``science.json`` (plan, checkpoints).

``--combine`` replaces stages 1-3: finished studies of different environments (run as
separate processes, say one per core) are gathered into ``--out`` and stage 4 runs over
all of them; each environment keeps its own number of training seeds, and the verdict
asks for 3 (eval.reporting.multiseed.MIN_SEEDS) whatever the intervals say.

``--export DEST`` copies a finished study's portable part (``science.json``, the held-out
records, the references, each run's ``config.yaml``, ``episodes.csv``, ``manifest.json`` (commit,
task version) and ``state.json`` (training time, validation history), and the tested
checkpoints' provenance as ``checkpoints.json``: a few MB, no checkpoint) to ``DEST``, say
a docs/results page, with ``contact.csv`` (``studies/stops.py``'s per-policy lines of the
held-out records: each mean return without the contact charge, which stays in git where the
records do not; ``studies/contact_table.py`` reads it); ``--combine`` takes such a copy as a
study. A study whose machine is gone (run folders are not kept in git) still joins the final
table that way.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for path in (ROOT, ROOT / "studies"):  # run as a script from a checkout; studies/science_pages.py
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

import pandas as pd  # noqa: E402
import science_pages as pages  # noqa: E402

from agents.errors import AgentError  # noqa: E402
from agents.registry import ALGORITHMS  # noqa: E402
from cosim.errors import CosimError  # noqa: E402
from eval.labels import ENVS  # noqa: E402
from eval.reporting import multiseed, stats  # noqa: E402
from eval.reporting.report import env_title  # noqa: E402
from eval.scale.benchmark import (  # noqa: E402
    TEST_SETTINGS,
    BenchmarkPlan,
    adds_seeds,
    cell_name,
    finished_runs,
    load_plan,
    saved_plan,
)
from eval.testing.protocol import ProtocolPlan, rules  # noqa: E402
from eval.testing.validity import DEGENERATE, HELD_OUT_SEED, POLICIES  # noqa: E402
from eval.training.config import COLLISION_RULES  # noqa: E402
from eval.training.presets import load_presets  # noqa: E402

SMOKE = {"preset": "smoke", "envs": ["env_1"], "algos": ["ppo", "dqn"], "seeds": 2, "steps": 60,
         "scenarios": [1]}


class ScienceError(CosimError, ValueError):
    """The study cannot run as asked; the message says what to change."""


def default_preset() -> str:
    """``standard`` once eval/training/hyperparams defines it, else ``quick``."""
    return "standard" if "standard" in load_presets() else "quick"


def parse(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--smoke", action="store_true",
                   help="the CI study: --preset smoke --envs env_1 --algos ppo dqn --seeds 2 "
                        "--steps 60 --scenarios 1 --no-ray (options given explicitly win)")
    p.add_argument("--preset", default=None, help=f"training budget (default: {default_preset()})")
    p.add_argument("--envs", nargs="+", default=None, help="default: env_1 .. env_5")
    p.add_argument("--algos", nargs="+", default=None, help="default: all six")
    p.add_argument("--seeds", type=int, default=None,
                   help="training seeds 0..K-1 (default 3); a larger K on a finished study adds seeds")
    p.add_argument("--first-seed", type=int, default=None, metavar="S",
                   help="train and test seeds S..S+K-1 (default 0): one part of a grid run in parts, "
                        "e.g. --first-seed 1 --seeds 1 for seed 1 alone; --combine joins the parts")
    p.add_argument("--steps", type=int, default=None, help="environment steps per trial "
                                                           "(default: the preset's)")
    p.add_argument("--agents", type=int, default=None,
                   help="ACs each training run drives (default: the preset's; the test always "
                        "drives one AC per algorithm)")
    p.add_argument("--collisions", choices=COLLISION_RULES, default=None,
                   help="training episodes at a collision: continue (default, the test's rule) or "
                        "end (the paper's); the test never ends them")
    p.add_argument("--obs", choices=("image", "nav"), default=None,
                   help="what the ACs observe in training and test (as `cosim train --obs`; "
                        "default image, the paper's)")
    p.add_argument("--share-params", action="store_true", default=None,
                   help="one network per run for all its ACs in ppo dqn ddpg td3 (as `cosim "
                        "train --share-params`; default: one per AC, the paper's)")
    p.add_argument("--demo-steps", type=int, default=None, metavar="N",
                   help="the demonstration variant (as `cosim benchmark --demo-steps`): dqn ddpg "
                        "td3 learn from N env steps of the autopilot too; default 0: off")
    p.add_argument("--episodes", type=int, default=None,
                   help="test episodes per environment and seed (default: the preset's test)")
    p.add_argument("--test-steps", type=int, default=None, help="steps per test episode")
    p.add_argument("--scenarios", nargs="+", type=int, choices=[1, 2], default=None,
                   help="test scenarios (default 1 2; the verdict and IQM use Scenario 1)")
    p.add_argument("--test-workers", type=int, default=os.cpu_count() or 1, metavar="N",
                   help="processes that run the held-out test (default: one per core; the records "
                        "are the same with any number)")
    p.add_argument("--no-ray", action="store_true", help="train one trial after another, no Ray")
    p.add_argument("--concurrent", type=int, default=None, help="Ray trials at once")
    p.add_argument("--ray-address", default=None, help="an existing Ray cluster")
    p.add_argument("--out", type=Path, default=Path("science"), help="study folder")
    p.add_argument("--combine", nargs="+", type=Path, default=None, metavar="STUDY",
                   help="instead of running a study: gather finished studies of different "
                        "environments (same algorithms, preset and test) into --out and write "
                        "the results over all of them")
    p.add_argument("--export", type=Path, default=None, metavar="DEST",
                   help="instead of running a study: copy the finished study at --out, without "
                        "its checkpoints, to DEST (a folder --combine takes)")
    p.add_argument("--runs", nargs="+", type=Path, default=None, metavar="BENCH",
                   help="instead of training: link this study's finished runs from these "
                        "`cosim benchmark --train-only` folders (checked against the plan)")
    p.add_argument("--quiet", action="store_true")
    args = p.parse_args(argv)
    if args.test_workers < 1:
        p.error(f"--test-workers {args.test_workers}: give 1 or more processes")
    if args.first_seed is not None and args.first_seed < 0:
        p.error(f"--first-seed {args.first_seed}: give 0 or more (the first training seed)")
    given = {k for k, v in vars(args).items() if v is not None}
    study_options = given & {"preset", "envs", "algos", "seeds", "first_seed", "steps", "agents", "collisions", "episodes",
                             "obs", "share_params", "demo_steps",
                             "test_steps", "scenarios", "concurrent", "ray_address", "runs"}
    if args.combine and (study_options or args.smoke):
        p.error("--combine takes the studies' own settings; drop --"
                + ", --".join(sorted(k.replace("_", "-") for k in study_options) or ["smoke"]))
    if args.export and (study_options or args.smoke or args.combine):
        p.error("--export copies the finished study at --out as it is; drop --"
                + ", --".join(sorted(k.replace("_", "-") for k in study_options)
                              or (["combine"] if args.combine else ["smoke"])))
    if args.smoke:
        for k, v in SMOKE.items():
            if k not in given:
                setattr(args, k, v)
        args.no_ray = True
    args.preset = args.preset or default_preset()
    args.envs = args.envs or list(ENVS)
    args.algos = args.algos or list(ALGORITHMS)
    args.seeds = 3 if args.seeds is None else args.seeds
    args.scenarios = sorted(set(args.scenarios or [1, 2]))
    return args


def test_settings(args) -> tuple[int, int]:
    """(episodes, steps) of the test: the options, else the preset's `cosim benchmark` test,
    else the protocol's defaults (3 episodes of the scenario's horizon: steps None)."""
    from eval.testing.protocol import ProtocolPlan

    base = TEST_SETTINGS.get(args.preset)
    episodes = args.episodes or (base.episodes if base else ProtocolPlan.episodes)
    steps = args.test_steps or (base.steps if base else ProtocolPlan.steps)
    if episodes < 1 or (steps is not None and steps < 1):
        raise ScienceError(f"--episodes and --test-steps must be >= 1, got {episodes} and {steps}")
    return episodes, steps


def study_plan(args, plan: BenchmarkPlan) -> dict:
    episodes, steps = test_settings(args)
    return {"benchmark": plan.to_dict(), "test": {
        "episodes": episodes, "steps": steps, "scenarios": sorted(args.scenarios),
        "episode_seeds": [HELD_OUT_SEED + e for e in range(episodes)],
        "collisions_end_episode": False, **rules(ProtocolPlan())}}


def check_plan(out: Path, study: dict) -> None:
    """science.json: the plan a rerun must repeat (its cached test records depend on it).

    Only ``--seeds`` may grow: the finished seeds' runs and test records are kept (a seed's
    test uses that seed's checkpoints only), the new seeds are trained and tested.
    """
    saved = out / "science.json"
    if saved.exists():
        old = json.loads(saved.read_text())
        old["benchmark"] = {"collisions": "end", **old["benchmark"]}  # saved before it was recorded
        kept = {k: old.get(k) for k in study}
        if kept == study:
            return
        if not (kept["test"] == study["test"] and adds_seeds(kept["benchmark"], study["benchmark"])):
            raise ScienceError(f"{out} holds a study started with {old['benchmark']} and test "
                               f"{old['test']}; repeat those options (only --seeds may grow) "
                               "or choose another --out")
    out.mkdir(parents=True, exist_ok=True)
    saved.write_text(json.dumps(study, indent=2))


# -- 1. training -----------------------------------------------------------------------------
def train(args, plan: BenchmarkPlan, bench: Path, say) -> None:
    """`cosim benchmark --train-only` (with --resume once started); skipped when done."""
    cells = [cell_name(c) for c in plan.cells()]
    saved = bench / "benchmark.json"
    if saved.exists() and saved_plan(saved) == plan.to_dict() and len(
            finished_runs(plan, bench)) == len(cells):
        say(f"training: all {len(cells)} runs finished in {bench / 'runs'}")
        return
    cmd = [sys.executable, "-m", "eval.cli", "benchmark", "--preset", plan.preset,
           "--envs", *plan.envs, "--algos", *plan.algos, "--seeds", str(plan.seeds),
           "--out", str(bench), "--train-only"]
    if plan.first_seed:
        cmd += ["--first-seed", str(plan.first_seed)]
    if plan.steps:
        cmd += ["--steps", str(plan.steps)]
    if plan.agents:
        cmd += ["--agents", str(plan.agents)]
    if plan.collisions:
        cmd += ["--collisions", plan.collisions]
    if plan.obs != "image":
        cmd += ["--obs", plan.obs]
    if plan.share_params:
        cmd.append("--share-params")
    if plan.demo_steps:
        cmd += ["--demo-steps", str(plan.demo_steps)]
    if saved.exists():
        cmd.append("--resume")
    if args.no_ray:
        cmd.append("--no-ray")
    if args.concurrent:
        cmd += ["--concurrent", str(args.concurrent)]
    if args.ray_address:
        cmd += ["--ray-address", args.ray_address]
    if args.quiet:
        cmd.append("--quiet")
    say("training: cosim " + " ".join(cmd[3:]))
    done = subprocess.run(cmd, cwd=ROOT)
    if done.returncode:
        raise ScienceError(f"training stopped (cosim benchmark exit {done.returncode}); rerun "
                           "the same command to continue from the finished trials")


HOW_KEYS = ("device", "torch_threads", "learner_threads")
"""Config keys a linked run may differ in from its cell: where and on how many threads it
ran, not what it learned from (every other key must match)."""


def adopt(plan: BenchmarkPlan, bench: Path, sources: list[Path], say) -> None:
    """Stage 1 from runs trained elsewhere: link each cell's finished run from one of the
    ``sources`` (``cosim benchmark --train-only`` folders) into ``bench/runs`` and record the
    plan, so that :func:`train` finds every run done."""
    from eval.training.runfolder import load_run_config

    links = {}
    for cfg in plan.cells():
        name = cell_name(cfg)
        found = [s.resolve() / "runs" / name for s in sources if (s / "runs" / name).is_dir()]
        if len(found) != 1:
            where = (f"in both {found[0].parents[1]} and {found[1].parents[1]}" if found
                     else f"in none of {', '.join(map(str, sources))}")
            raise ScienceError(f"--runs: the finished run {name} is {where}; give each run once "
                               "(finish it with `cosim benchmark ... --train-only --resume`)")
        # through JSON: config.yaml holds lists where the config holds tuples
        ran, want = (json.loads(json.dumps(c.to_dict())) for c in (load_run_config(found[0]), cfg))
        diff = [k for k in want if k not in HOW_KEYS and ran[k] != want[k]]
        if diff:
            raise ScienceError(f"--runs: {found[0]} was trained with another {', '.join(diff)} than "
                               "this study's plan; give the study that run's options or retrain it")
        links[name] = found[0]
    (bench / "runs").mkdir(parents=True, exist_ok=True)
    for name, src in links.items():
        link = bench / "runs" / name
        if link.is_symlink() or link.exists():
            if link.resolve() != src.resolve():
                raise ScienceError(f"{link} already holds another run; choose another --out")
            continue
        link.symlink_to(src)
    saved = bench / "benchmark.json"
    old = saved_plan(saved) if saved.exists() else None
    if old is not None and old != plan.to_dict() and not adds_seeds(old, plan):
        raise ScienceError(f"{saved} holds another plan; choose another --out")
    saved.write_text(json.dumps(plan.to_dict()))
    say(f"training: {len(links)} finished runs linked from {', '.join(map(str, sources))}")


# -- 2. test on held-out seeds ------------------------------------------------------------------
def checkpoints(plan: BenchmarkPlan, bench: Path, env: str, seed: int) -> dict[str, Path]:
    from eval.testing import selection

    found = {}
    for algo in plan.algos:
        run = bench / "runs" / cell_name({"env": env, "algo": algo, "seed": seed})
        chosen = selection.choose(run)
        if chosen is None:
            raise ScienceError(f"{run}: no checkpoint; rerun the same command to train it")
        found[algo] = chosen.path
    return found


EXPORTED = "checkpoints.json"
"""An exported study's provenance of every checkpoint it tested (the files stayed behind)."""
RUN_RECORDS = ("manifest.json", "state.json")
"""Of a run folder, beside config.yaml and episodes.csv, what an export keeps where the run has
it: the commit, task version, package versions and scenario files' SHA-256 it trained with
(manifest.json), and its training time, validation history and best scores per AC (state.json)."""


def tested_checkpoints(plan: BenchmarkPlan, out: Path, seeds_of: dict[str, list[int]]) -> list[dict]:
    """One ``{"env", "seed", "algorithm", "path"}`` per tested checkpoint (environments in
    ``seeds_of``'s order) from the run folders under ``out/bench``; where a run is an exported
    copy (no checkpoint), the provenance entry its export recorded (``checkpoints.json``, with
    its SHA-256), as it was."""
    saved = out / EXPORTED
    exported = {(c["env"], c["seed"], c["algorithm"]): c
                for c in (json.loads(saved.read_text()) if saved.is_file() else [])}
    every = []
    for e, seeds in seeds_of.items():
        for s in seeds:
            if all((e, s, a) in exported for a in plan.algos):
                every += [exported[(e, s, a)] for a in plan.algos]
            else:
                every += [{"env": e, "seed": s, "algorithm": a, "path": p}
                          for a, p in checkpoints(plan, out / "bench", e, s).items()]
    return every


def export(out: Path, dest: Path, say) -> None:
    """Copy the finished study at ``out`` to ``dest`` without its checkpoints: science.json,
    seeds.csv, test/ and references/, each run's config.yaml and episodes.csv (what stage 4
    reads of a run) and its :data:`RUN_RECORDS`, and the tested checkpoints' provenance
    (:data:`EXPORTED`)."""
    import shutil

    from eval.reporting.report import checkpoint_provenance

    saved = out / "science.json"
    study = json.loads(saved.read_text()) if saved.is_file() else {}
    if "checkpoints" not in study:
        raise ScienceError(f"--export: {out} holds no finished study (no results yet); run "
                           "its own command to the end first")
    if "combined" in study:
        raise ScienceError(f"--export: {out} is a combination; export each of its studies")
    if dest.resolve() == out:
        raise ScienceError(f"--export {dest}: that is the study itself; give another folder")
    if dest.exists() and any(dest.iterdir()) and not (dest / "science.json").is_file():
        raise ScienceError(f"--export {dest}: that folder holds something else; give an empty "
                           "or new one")
    plan = load_plan(out / "bench")
    seeds_of = {e: list(plan.seed_list) for e in plan.envs}
    entries = checkpoint_provenance("trained", tested_checkpoints(plan, out, seeds_of))
    files = [saved, out / "seeds.csv"] + [out / "references" / f"{e}.csv" for e in plan.envs] + [
        out / "test" / f"{e}__seed{k}.parquet" for e in plan.envs for k in plan.seed_list]
    for cfg in plan.cells():
        run = out / "bench" / "runs" / cell_name(cfg)
        files += [run / "config.yaml", run / "episodes.csv"]
        files += [run / name for name in RUN_RECORDS if (run / name).is_file()]
    for f in files:
        target = dest / f.relative_to(out)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(f, target)  # through a run's link, to the file itself
    (dest / EXPORTED).write_text(json.dumps(entries, indent=2, default=str))
    contact(sorted((dest / "test").glob("*.parquet")), dest / "contact.csv")
    size = sum(f.stat().st_size for f in dest.rglob("*") if f.is_file())
    say(f"exported {out} to {dest}: {len(files) + 2} files, {size / 1e6:.1f} MB")


def contact(records: list[Path], dest: Path) -> None:
    """``dest``: the per-policy lines (``studies/stops.py --policy-out``) of a study's held-out
    records files, one per (policy, environment, scenario, training seed)."""
    from stops import by_policy, episode_rows  # its sibling in studies/ (on the path as a script)

    by_policy(pd.concat([episode_rows(r) for r in records], ignore_index=True)).to_csv(dest, index=False)


def _write(df: pd.DataFrame, path: Path) -> None:
    """Write next to ``path`` and rename into place: a cached file exists only complete."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    if path.suffix == ".parquet":
        df.to_parquet(tmp, index=False)
    else:
        df.to_csv(tmp, index=False)
    tmp.replace(path)


def test(plan: BenchmarkPlan, study: dict, out: Path, say, seeds_of: dict[str, list[int]],
         workers: int = 1) -> pd.DataFrame:
    """Held-out records of every (env, training seed in seeds_of[env]), from the cache where
    present; ``workers`` processes run each seed's episodes (the same records as one). A
    combined (env, seed) whose records stayed on another machine has its seed means instead
    (:data:`KEPT`): it is skipped here and joins the results in :func:`kept_seeds`. Each
    (env, seed) is one test session (eval.testing.session.run_test), as `cosim test`'s."""
    from eval.testing.protocol import ProtocolPlan
    from eval.testing.session import TestRequest, run_test

    t = study["test"]
    frames = []
    for env in plan.envs:
        for seed in seeds_of[env]:
            path = out / "test" / f"{env}__seed{seed}.parquet"
            if not path.exists() and (out / "test" / KEPT.format(env=env, seed=seed)).is_file():
                continue
            if not path.exists():
                start = time.monotonic()
                pp = ProtocolPlan(envs=(env,), scenarios=tuple(t["scenarios"]),
                                  episodes=t["episodes"], steps=t["steps"], seed=HELD_OUT_SEED,
                                  agents=len(plan.algos))
                records = run_test(TestRequest(pp, tuple(plan.algos), workers=workers, checkpoints={
                    env: checkpoints(plan, out / "bench", env, seed)})).records
                _write(records.assign(train_seed=seed), path)
                say(f"tested {env} seed {seed} ({time.monotonic() - start:.0f} s)")
            frames.append(pd.read_parquet(path))
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


KEPT = "{env}__seed{seed}.seeds.csv"
"""In a combination's test/: the seed means (seeds.csv rows) of an (environment, seed) whose
held-out records are not here, gathered from an exported study (its records are generated data,
kept out of git): the tables, verdict and IQM take them as they are; the pooled report leaves
that seed out."""


def kept_seeds(out: Path, seeds_of: dict[str, list[int]], records: pd.DataFrame) -> pd.DataFrame:
    """The seed means of every (env, seed) of ``seeds_of`` without records in ``records``."""
    have = set(zip(records["env"], records["train_seed"], strict=True)) if len(records) else set()
    frames = [pd.read_csv(out / "test" / KEPT.format(env=e, seed=k))
              for e, seeds in seeds_of.items() for k in seeds if (e, k) not in have]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def references(plan: BenchmarkPlan, study: dict, out: Path, say) -> pd.DataFrame:
    """Reference rows per environment (Scenario 1 conditions, the same episode seeds)."""
    from eval.testing import validity

    t = study["test"]
    frames = []
    for env in plan.envs:
        path = out / "references" / f"{env}.csv"
        if not path.exists():
            start = time.monotonic()
            rows = validity.check_scenario(env, len(plan.algos), t["episodes"], t["steps"],
                                           policies=POLICIES)
            _write(rows.assign(env=env), path)
            say(f"references {env} ({time.monotonic() - start:.0f} s)")
        frames.append(pd.read_csv(path))
    return pd.concat(frames, ignore_index=True)


# -- combining finished studies ---------------------------------------------------------------
COMBINED_KEYS = ("preset", "algos", "steps", "agents", "collisions", "obs", "share_params", "demo_steps")
"""What the studies combined must share (with their whole test plan)."""


def combine(sources: list[Path], out: Path, say) -> tuple[BenchmarkPlan, dict, dict[str, list[int]]]:
    """Gather finished studies (same algorithms, preset, budget and test) of different
    environments, or of one environment's different seeds (``--first-seed``), into ``out``: run
    folders linked, held-out records (or, from an export without them, its seed means) and
    references copied. Returns the combined plan (seeds: the most any environment has), the
    study record and the training seeds of each environment. Lets environments and seeds train
    in separate processes, sessions or machines and still give one table and one IQM."""
    studies = []
    for src in sources:
        src = src.resolve()
        saved = src / "science.json"
        if not saved.is_file():
            raise ScienceError(f"--combine {src}: no science.json there; give the --out folder "
                               "of a studies/science.py study")
        study = json.loads(saved.read_text())
        study["benchmark"] = {"collisions": "end", **study["benchmark"]}  # saved before it was recorded
        studies.append((src, study))
    (src0, first), b0 = studies[0], studies[0][1]["benchmark"]
    seeds_of: dict[str, list[int]] = {}
    for src, st in studies:
        b = st["benchmark"]
        if "combined" in st:
            raise ScienceError(f"--combine {src}: already a combination; give its sources")
        diff = [k for k in COMBINED_KEYS if b.get(k) != b0.get(k)]
        if diff or st["test"] != first["test"]:
            what = ", ".join(diff + (["test"] if st["test"] != first["test"] else []))
            raise ScienceError(f"--combine: {src} differs from {src0} in {what}; combine only "
                               "studies run with the same algorithms, preset, steps and test")
        own = list(_study_seeds(b))
        for env in b["envs"]:
            twice = sorted(set(own) & set(seeds_of.get(env, [])))
            if twice:
                raise ScienceError(f"--combine: {env} seed {twice[0]} is in two of the studies; "
                                   "give each (environment, seed) once")
            seeds_of[env] = sorted(seeds_of.get(env, []) + own)
    envs = [e for e in ENVS if e in seeds_of] + sorted(set(seeds_of) - set(ENVS))
    plan = BenchmarkPlan(preset=b0["preset"], envs=tuple(envs), algos=tuple(b0["algos"]),
                         seeds=max(map(len, seeds_of.values())), steps=b0["steps"], agents=b0.get("agents"),
                         collisions=b0.get("collisions"), obs=b0.get("obs", "image"),
                         share_params=bool(b0.get("share_params", False)),
                         demo_steps=int(b0.get("demo_steps", 0)))
    saved = out / "science.json"
    if saved.exists() and "combined" not in json.loads(saved.read_text()):
        raise ScienceError(f"{out} holds a study of its own; choose another --out for the "
                           "combination")
    for src, st in studies:
        for env in st["benchmark"]["envs"]:
            _gather(src, env, _study_seeds(st["benchmark"]), plan.algos, out, say)
    exported = [c for src, _ in studies if (src / EXPORTED).is_file()
                for c in json.loads((src / EXPORTED).read_text())]
    if exported:
        (out / EXPORTED).write_text(json.dumps(exported, indent=2))
    study = {"benchmark": {**plan.to_dict(), "seeds": seeds_of}, "test": first["test"],
             "combined": [str(src) for src, _ in studies]}
    saved.write_text(json.dumps(study, indent=2))
    say(f"combined {len(studies)} studies: " + ", ".join(f"{e} (seeds {' '.join(map(str, k))})"
                                                       for e, k in seeds_of.items()))
    return plan, study, seeds_of


def _study_seeds(bench: dict) -> range:
    """The training seeds of a study from its saved plan (``BenchmarkPlan.seed_list``; a plan
    saved before ``first_seed`` existed starts at 0)."""
    first = int(bench.get("first_seed", 0))
    return range(first, first + int(bench["seeds"]))


def _gather(src: Path, env: str, seeds, algos, out: Path, say) -> None:
    """Copy one environment's references and held-out records of the study ``src`` into
    ``out`` (a seed whose records are not there: its rows of ``src/seeds.csv``, :data:`KEPT`),
    and link its run folders."""
    import shutil

    means = pd.read_csv(src / "seeds.csv") if (src / "seeds.csv").is_file() else None
    refs = src / "references" / f"{env}.csv"
    records, kept = {}, {}  # seed -> its held-out records file, or its seed means
    for k in seeds:
        rec = src / "test" / f"{env}__seed{k}.parquet"
        rows = (means[(means["env"] == env) & (means["train_seed"] == k)]
                if means is not None and not rec.is_file() else None)
        if rows is not None and len(rows):
            kept[k] = rows
        else:
            records[k] = rec
    missing = [f for f in [refs, *records.values()] if not f.is_file()]
    if missing:
        raise ScienceError(f"--combine: {missing[0]} is missing; finish that study first "
                           "(rerun its own command)")
    for folder in ("test", "references"):
        (out / folder).mkdir(parents=True, exist_ok=True)
    shutil.copy2(refs, out / "references" / refs.name)
    for k, rec in records.items():
        shutil.copy2(rec, out / "test" / rec.name)
        (out / "test" / KEPT.format(env=env, seed=k)).unlink(missing_ok=True)
    for k, rows in kept.items():
        (out / "test" / f"{env}__seed{k}.parquet").unlink(missing_ok=True)
        _write(rows, out / "test" / KEPT.format(env=env, seed=k))
        say(f"{env} seed {k}: {src} holds no held-out records; its seed means (seeds.csv) join "
            "the tables, the pooled report leaves it out")
    for algo in algos:
        for k in seeds:
            name = cell_name({"env": env, "algo": algo, "seed": k})
            link = out / "bench" / "runs" / name
            link.parent.mkdir(parents=True, exist_ok=True)
            if link.is_symlink():
                link.unlink()
            if not link.exists():
                link.symlink_to(src / "bench" / "runs" / name, target_is_directory=True)


# -- 4. results -------------------------------------------------------------------------------
def results(plan: BenchmarkPlan, study: dict, records: pd.DataFrame, refs: pd.DataFrame,
            out: Path, command: str, seeds_of: dict[str, list[int]]) -> str:
    """Every results file; returns summary.md's text. ``seeds_of``: the training seeds of each
    environment (``plan.seed_list`` each, except in a --combine'd study)."""
    from eval.reporting.report import provenance, write_paper_report
    from eval.testing.protocol import ProtocolPlan

    kept = kept_seeds(out, seeds_of, records)
    measured = [multiseed.records_seed_means(records)] if len(records) else []
    seeds = pd.concat(measured + ([kept] if len(kept) else []), ignore_index=True)
    table = multiseed.seed_table(seeds)
    ref_table = multiseed.reference_table(refs)
    verdict = multiseed.verdict(table, ref_table)
    iqm = multiseed.iqm_table(seeds, ref_table)
    bench = out / "bench"
    runs = {(a, e, s): bench / "runs" / cell_name({"env": e, "algo": a, "seed": s})
            for e in plan.envs for a in plan.algos for s in seeds_of[e]}
    curves = pages.convergence_curves(runs)
    budgets = multiseed.budget_check(runs)

    seeds.to_csv(out / "seeds.csv", index=False)
    pd.concat([table, ref_table], ignore_index=True).to_csv(out / "results.csv", index=False)
    verdict.to_csv(out / "verdict.csv", index=False)
    iqm.to_csv(out / "iqm.csv", index=False)
    curves.to_csv(out / "convergence.csv", index=False)
    budgets.to_csv(out / "budget.csv", index=False)
    pages.convergence_figure(curves, out)
    pages.verdict_figure(verdict, seeds, ref_table[ref_table["scenario"] == 1], out)
    pages.iqm_figure(iqm, out)

    t = study["test"]
    b = plan.to_dict()
    budget = f", {b['steps']} steps per trial" if b["steps"] else ""
    budget += f", {plan.agents} ACs per training run" if plan.agents else ""
    budget += {"event": ", collisions do not end training episodes, one charge per event",
               "step": ", collisions do not end training episodes, every contact step charged "
                       "(`--collisions step`)"}.get(plan.collisions, "")
    budget += ", ACs observe camera frames and the nav measurements (`--obs nav`)" if plan.obs == "nav" else ""
    budget += (", one network per run for all its ACs in PPO, DQN, DDPG and TD3 (`--share-params`)"
               if plan.share_params else "")
    budget += (f", DQN, DDPG and TD3 learn from {plan.demo_steps} env steps of the autopilot's "
               "driving too (`--demo-steps`, the demonstration variant)" if plan.demo_steps else "")
    counts = sorted({len(k) for k in seeds_of.values()})
    per_env = (f"{counts[0]} seed(s)" if len(counts) == 1 else "seeds per environment: " + ", ".join(
        f"{env_title(e)} {len(seeds_of[e])}" for e in plan.envs))
    how = (f"{len(plan.algos)} algorithm(s) x {len(plan.envs)} environment(s) x {per_env}, "
           f"preset `{b['preset']}`{budget}; "
           f"tested on {t['episodes']} held-out episode(s) of {t['steps']} steps per (environment, "
           f"seed) (episode seeds {t['episode_seeds'][0]}.., collisions do not end an episode); "
           f"reference rows on the same episode seeds with {len(plan.algos)} ACs (Scenario 1 "
           f"conditions). Cells: mean over training seeds [95% percentile bootstrap CI over "
           f"seeds, {stats.BOOTSTRAP} resamples]; reference rows: over episodes x ACs.")
    full = ["# Science study: full results\n", how + "\n"]
    for s in t["scenarios"]:
        full.append(f"\n## Scenario {s} ({'multi-agent' if s == 1 else 'single-agent'})\n")
        full.append(pages.metrics_markdown(table, ref_table, s))
    (out / "results.md").write_text("\n".join(full))
    (out / "verdict.md").write_text(multiseed.verdict_markdown(verdict))
    (out / "iqm.md").write_text(multiseed.iqm_markdown(iqm))
    goals = pages.targets(verdict)
    goals.to_csv(out / "targets.csv", index=False)

    passed = int(verdict["passed"].sum())
    summary = [
        "### Science study results\n", f"`{command}`: {how}\n",
        "Driving score (DS = route completion x infraction penalty, docs/task.md \"Driving score\"), "
        "Scenario 1 (multi-agent):\n", pages.grid_markdown(table, "DS", 1, ref_table),
        "\nRoute completion, Scenario 1:\n", pages.grid_markdown(table, "RC", 1, ref_table),
        "\nSuccess rate (goal reached with no infraction), Scenario 1:\n",
        pages.grid_markdown(table, "success", 1, ref_table),
        "\nRoute completion of the turning slots (the AC-episodes whose slot's route turns; turns are "
        "learned where its CI's lower end clears the safe non-turner's), Scenario 1:\n",
        pages.grid_markdown(table, "RC_turning", 1, ref_table, ("autopilot", "safe-non-turner", "random")),
        "\nReturn, Scenario 1:\n", pages.grid_markdown(table, "return", 1, ref_table),
        "\nGoal rate, Scenario 1:\n", pages.grid_markdown(table, "goal", 1, ref_table),
        "\nGoal rate of the turning slots (the AC-episodes whose slot's route turns), Scenario 1:\n",
        pages.grid_markdown(table, "goal_turning", 1, ref_table),
        *(["\nAlone (Scenario 2, each algorithm's `ac_0` with no other AC): return [95% CI over seeds] "
           "(goal rate):\n", pages.return_goal_grid_markdown(table, 2)] if 2 in t["scenarios"] else []),
        f"\nValidity verdict (issue 61): {passed} of {len(verdict)} (algorithm, "
        "environment) pairs have a driving score whose 95% CI's lower end clears every degenerate "
        f"reference's ({', '.join(DEGENERATE)}), over at least {multiseed.MIN_SEEDS} training "
        "seeds ('not shown': above with fewer seeds); ', turns': the turning slots' route completion "
        "CI's lower end clears the safe non-turner's. Driving score [95% CI over seeds] (goal rate) "
        "and verdict per pair:\n",
        pages.verdict_grid_markdown(verdict, ref_table[ref_table.scenario == 1]),
        "\nThe same drawn (`verdict.png` / `verdict.pdf`): per environment each algorithm's "
        "seed means (dots) and mean with its 95% CI over seeds of the driving score (top, against the "
        "autopilot and the best degenerate reference) and of the turning slots' route completion "
        "(bottom, against the autopilot and the safe non-turner).\n",
        "\nEach pair with what failed:\n", multiseed.verdict_markdown(verdict),
        "\nIQM across environments (Scenario 1 driving score normalised per environment: uniform "
        "random = 0, autopilot = 1; interquartile mean of every (environment, seed) score; "
        "95% stratified bootstrap CI resampling seeds within environments):\n",
        multiseed.iqm_markdown(iqm),
        "\nThe same drawn: `iqm.png` / `iqm.pdf`.\n",
        f"\nIssue 27's target per environment: {int(goals['met'].sum())} of {len(goals)} met (a "
        "discrete and a continuous algorithm pass the verdict; where a route turns, some "
        "algorithm's turns are learned):\n", pages.targets_markdown(goals),
        f"\nDid the budgets suffice? Training return of the last {multiseed.PLATEAU_FRACTION:.0%} of each "
        f"run's budget minus the {multiseed.PLATEAU_FRACTION:.0%} before (mean over seeds); rising k/n: in k "
        "of n seeds the 95% bootstrap interval over AC-episodes lies above 0, so the curve had "
        "not flattened (bold); 0/n says no clear rise, which noisy returns can also give "
        "(`budget.csv`):\n", multiseed.budget_markdown(budgets),
        "\nConvergence (training return against environment steps, mean over seeds, band: "
        "min-max over seeds): `convergence.png` / `convergence.pdf`. Every metric with "
        "reference rows: `results.md`.\n"]
    text = "\n".join(summary)
    (out / "summary.md").write_text(text)

    # the `cosim test` report of the held-out records, seeds pooled (episodes renumbered)
    every = tested_checkpoints(plan, out, seeds_of)
    left_out = sorted({f"{env_title(e)} seed {k}" for e, k in
                       zip(kept.get("env", []), kept.get("train_seed", []), strict=True)})
    if not len(records):
        import shutil

        shutil.rmtree(out / "report", ignore_errors=True)  # a combination's earlier report
        _record_checkpoints(study, every, out)
        return text + "\nNo held-out records here (every seed's means came from an export): no report.\n"
    pooled = records.assign(episode=records["train_seed"] * t["episodes"] + records["episode"])
    whole = ProtocolPlan(envs=tuple(plan.envs), scenarios=tuple(t["scenarios"]),
                         episodes=t["episodes"], steps=t["steps"], seed=HELD_OUT_SEED,
                         agents=len(plan.algos))
    first = {c["algorithm"]: c["path"] for c in every
             if c["env"] == plan.envs[0] and c["seed"] == seeds_of[plan.envs[0]][0] and "path" in c}
    prov = provenance(policy="trained", plan=whole, algos=list(plan.algos), checkpoints=first,
                      command=command.split()[1:], env_checkpoints=every, benchmark=plan.to_dict())
    write_paper_report(pooled, out / "report", prov=prov, extra_md=(
        f"\n## Science study\n\nTraining seeds pooled ({per_env}): episode = seed x "
        f"{t['episodes']} + test episode. Provenance lists every checkpoint (environment, "
        "seed, algorithm); science.json too.\n" + (
            f"\nNot in this report (their held-out records stayed where they were made; their "
            f"seed means are in the study's tables): {', '.join(left_out)}.\n" if left_out else "")))
    _record_checkpoints(study, every, out)  # last: a study with its checkpoints recorded is finished
    return text


def _record_checkpoints(study: dict, every: list[dict], out: Path) -> None:
    """science.json: the study record with every tested checkpoint (path, or an export's entry)."""
    study["checkpoints"] = {}
    for c in every:
        where = str(c["path"].relative_to(out)) if "path" in c else c["checkpoint"]
        study["checkpoints"].setdefault(f"{c['env']}__seed{c['seed']}", {})[c["algorithm"]] = where
    (out / "science.json").write_text(json.dumps(study, indent=2))


def main(argv=None) -> int:
    args = parse(argv)
    say = (lambda text: None) if args.quiet else (lambda text: print(text, file=sys.stderr, flush=True))
    start = time.monotonic()
    try:
        out = args.out.resolve()
        if args.export:
            export(out, args.export, say)
            return 0
        if args.combine:
            plan, study, seeds_of = combine(args.combine, out, say)
        else:
            plan = BenchmarkPlan(preset=args.preset, envs=tuple(args.envs),
                                 algos=tuple(args.algos), seeds=args.seeds, steps=args.steps,
                                 agents=args.agents, collisions=args.collisions or "event",
                                 obs=args.obs or "image", share_params=bool(args.share_params),
                                 demo_steps=args.demo_steps or 0, first_seed=args.first_seed or 0)
            plan.cells()  # an unknown preset or environment fails here, before any work
            study = study_plan(args, plan)
            check_plan(out, study)
            if args.runs:
                adopt(plan, out / "bench", args.runs, say)
            train(args, plan, out / "bench", say)
            seeds_of = {e: list(plan.seed_list) for e in plan.envs}
        records = test(plan, study, out, say, seeds_of, args.test_workers)
        refs = references(plan, study, out, say)
        command = "python studies/science.py " + " ".join(sys.argv[1:] if argv is None else argv)
        text = results(plan, study, records, refs, out, command, seeds_of)
    except (CosimError, AgentError) as exc:
        print(f"science: error: {exc}", file=sys.stderr)
        return 2
    print(text)
    say(f"science study: {out} ({time.monotonic() - start:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
