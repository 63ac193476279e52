"""`cosim train --pbt P`: Population Based Training (Jaderberg et al. 2017) of one algorithm
on Ray Tune, P trials that copy the best and perturb its hyperparameters.

Each trial is an ordinary training run (:func:`eval.training.train.train`) that reports
``mean_return`` (mean episodic return over each AC's last 20 episodes) and its run
folder as a Tune checkpoint every ``--pbt-interval`` environment steps. At each
interval ``ray.tune.schedulers.PopulationBasedTraining`` (synchronous: all trials
at the same step) lets the bottom quarter of the population continue from a
checkpoint of the top quarter (exploit) with hyperparameters perturbed (explore:
a neighbouring value of :data:`MUTATIONS`, sometimes resampled; at least one changed). A
trial restored from a checkpoint gets its new hyperparameters written into the
run's config.yaml and into every agent checkpoint (config and optimizer learning
rates) before ``train(resume=...)`` reloads them; a donor's replay buffer is not
copied (it is not checkpointed, eval/training/train.py). ``--resume`` restores Tune's
experiment; the scheduler's state, which Ray does not save, is rebuilt from the
restored trials (:class:`eval.scale.pbt_scheduler.ResumablePBT`).

The PBT folder ``<env>__<algo>__<seed>__pbt<P>-<stamp>/`` is the best trial's run
folder (what `cosim test` loads) plus::

    pbt.json        population, interval, base config (what --resume reads)
    lineage.csv     one row per exploit and hyperparameter: who cloned whom at which step,
                    the donor's value, the new value, the clone's previous value
    lineage.png     return per trial against steps with the exploits drawn, and the
                    learning rate of each trial
    trials.csv      final step, return and hyperparameters of every trial
    pbt/            Ray Tune's experiment (tune/), the trials' working run folders (trials/),
                    per-trial histories (history/) and exploit records (exploits/)
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import hashlib
import json
import logging
import random
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from agents.configs import AgentConfig
from eval.scale.benchmark import finite, train_cell
from eval.training.train import TrainConfig, TrainError

log = logging.getLogger(__name__)

_LR = (0.25, 0.5, 1.0, 2.0, 4.0)
"""Learning rates: these multiples of the preset's value."""

MUTATIONS: dict[str, dict[str, tuple]] = {
    # field -> candidate values; ("x", factors) scales the preset's value
    "ppo": {"learning_rate": ("x", _LR), "ent_coef": (0.0, 0.001, 0.005, 0.01, 0.02, 0.05),
            "clip_coef": (0.1, 0.2, 0.3), "gae_lambda": (0.9, 0.95, 0.98)},
    "dqn": {"learning_rate": ("x", _LR), "exploration_final_eps": (0.01, 0.02, 0.05, 0.1),
            "target_update_interval": ("x", (0.5, 1.0, 2.0))},
    "ddpg": {"actor_learning_rate": ("x", _LR), "critic_learning_rate": ("x", _LR),
             "exploration_noise": (0.05, 0.1, 0.2, 0.3)},
    "td3": {"actor_learning_rate": ("x", _LR), "critic_learning_rate": ("x", _LR),
            "exploration_noise": (0.05, 0.1, 0.2, 0.3), "policy_delay": (1, 2, 3)},
    "a3c": {"learning_rate": ("x", _LR), "ent_coef": (0.0, 0.005, 0.01, 0.02, 0.05),
            "vf_coef": (0.25, 0.5, 1.0)},
    "impala": {"learning_rate": ("x", _LR), "ent_coef": (0.0, 0.005, 0.01, 0.02, 0.05),
               "vf_coef": (0.25, 0.5, 1.0)},
}


def mutation_space(algo: str, agent_config: AgentConfig) -> dict[str, list]:
    """The values PBT may give each mutated hyperparameter of ``algo`` (typed like the config's
    field); Ray Tune's search space, the one place PBT's values are a dict (Ray's boundary)."""
    space = {}
    for name, values in MUTATIONS[algo].items():
        base = getattr(agent_config, name)
        if values and values[0] == "x":
            values = [type(base)(base * f) for f in values[1]]
        space[name] = sorted({type(base)(v) for v in values})
    return space


def with_hyper(cfg: TrainConfig, hyper: dict[str, Any]) -> TrainConfig:
    """``cfg`` with some agent hyperparameters changed: ``dataclasses.replace`` on its typed
    agent config (``AgentConfig.replace``, validated again by the agent's config class)."""
    return dataclasses.replace(cfg, agent_config=cfg.agent_config.replace(**hyper))


def apply_hyper(run: Path, cfg: TrainConfig) -> None:
    """Write ``cfg``'s hyperparameters into a run folder before it is resumed: config.yaml,
    and each agent checkpoint through agents' own API (``agents.checkpoint.retune_checkpoint``:
    the checkpoint's config and its optimizers' learning rates)."""
    from agents.checkpoint import retune_checkpoint

    (run / "config.yaml").write_text(yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    for path in sorted((run / "checkpoints").glob("ac_*/*.pt")):
        retune_checkpoint(path, cfg.agent_config)


def weights_digest(path: Path) -> str:
    """SHA-256 of an agent checkpoint's network weights (not its config or optimizer)."""
    import torch

    nets = torch.load(path, map_location="cpu", weights_only=True)["state"]["networks"]
    h = hashlib.sha256()
    for net in sorted(nets):
        for key in sorted(nets[net]):
            h.update(f"{net}.{key}".encode())
            h.update(nets[net][key].cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


# -- the trial ---------------------------------------------------------------------------
def _pbt_trial(config: dict) -> None:
    """Ray Tune function trainable of one PBT member (see the module docstring)."""
    from ray import tune

    trial = tune.get_context().get_trial_id()
    pbt = Path(config["pbt_dir"])
    hyper = {k: v for k, v in config.items() if k not in ("train", "pbt_dir")}
    # Ray's boundary: a trial's config is a dict (param_space); TrainConfig builds the typed
    # agent config from it once, and the trial's values change it by dataclasses.replace
    cfg = with_hyper(TrainConfig(**config["train"]), hyper)
    own = pbt / "hyper" / f"{trial}.json"
    previous = json.loads(own.read_text()) if own.exists() else None
    own.parent.mkdir(parents=True, exist_ok=True)
    history = pbt / "history" / f"{trial}.jsonl"
    history.parent.mkdir(parents=True, exist_ok=True)

    def report(run: Path, env_steps: int, mean_return: float) -> None:
        record = json.dumps({"trial": trial, "env_steps": env_steps,
                             "mean_return": finite(mean_return), "hyper": hyper})
        (run / "pbt_trial.json").write_text(record)  # the checkpoint's: who made it, with what
        with open(history, "a") as f:
            f.write(record + "\n")
        tune.report({"env_steps": env_steps, "mean_return": finite(mean_return)},
                    checkpoint=tune.Checkpoint.from_directory(str(run)))

    folder = pbt / "trials" / trial
    checkpoint = tune.get_checkpoint()
    if checkpoint is None:
        own.write_text(json.dumps(hyper))
        train_cell(cfg, folder, None, report)
        return
    with checkpoint.as_directory() as restored:
        restored = Path(restored)
        meta = json.loads((restored / "pbt_trial.json").read_text())
        exploit = meta["trial"] != trial  # this trial continues from another's checkpoint

        def prepare(run: Path) -> None:
            apply_hyper(run, cfg)
            if exploit:
                _record_exploit(pbt, trial, meta, hyper, previous, restored, run)
            # after the record, so that an interruption in between leaves the old values as
            # `previous` for the exploit that a resume applies again
            own.write_text(json.dumps(hyper))
            if meta["env_steps"] >= cfg.steps:  # cloned at the end: the clone's final result
                report(run, meta["env_steps"], meta["mean_return"])

        train_cell(cfg, folder, restored, report, prepare=prepare)


def _record_exploit(pbt: Path, trial: str, meta: dict, hyper: dict, previous: dict | None,
                    donor_run: Path, run: Path) -> None:
    """``exploits/<step>-<trial>.json``: who cloned whom at which step, the hyperparameters
    before and after, and digests of the donor's weights and of the weights resumed.

    A record already there is kept: a trial interrupted before it reported again restores
    the donor's checkpoint once more on ``--resume`` and applies the same exploit, by which
    time its own hyperparameters (``previous``) are already the new ones."""
    path = pbt / "exploits" / f"{meta['env_steps']:010d}-{trial}.json"
    if path.exists():
        return
    event = {"env_steps": meta["env_steps"], "trial": trial, "donor": meta["trial"],
             "donor_hyper": meta["hyper"], "new_hyper": hyper, "previous_hyper": previous,
             "donor_weights_sha256": weights_digest(donor_run / "checkpoints/ac_0/latest.pt"),
             "resumed_weights_sha256": weights_digest(run / "checkpoints/ac_0/latest.pt")}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(event, indent=1))
    tmp.replace(path)


# -- the driver --------------------------------------------------------------------------
def new_pbt_dir(out: Path, cfg: TrainConfig, population: int) -> Path:
    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    folder = Path(out) / f"{Path(cfg.env).stem}__{cfg.algo}__{cfg.seed}__pbt{population}-{stamp}"
    suffix = 1
    while folder.exists():
        folder = folder.with_name(f"{folder.name.rsplit('~', 1)[0]}~{suffix}")
        suffix += 1
    return folder


def run_pbt(cfg: TrainConfig | None, population: int = 4, interval: int | None = None,
            out: Path = Path("runs"), *, resume: Path | None = None, address: str | None = None,
            concurrent: int | None = None) -> Path:
    """Train a PBT population of ``cfg.algo`` (or continue one, ``resume``); return the PBT folder.

    Raises:
        TrainError: bad population or interval; a trial failed; the run was interrupted
            (naming the --resume command).
        eval.scale.raysession.RayError: Ray missing or the address does not answer.
    """
    from eval.scale.raysession import ray_session

    if resume is not None:
        folder = Path(resume).resolve()
        saved = json.loads((folder / "pbt.json").read_text())
        cfg, population, interval = TrainConfig(**saved["config"]), saved["population"], saved["interval"]
    else:
        interval = interval or cfg.checkpoint_every
        if population < 2 or interval < 1:
            raise TrainError(f"--pbt needs a population >= 2 and --pbt-interval >= 1, got "
                             f"{population} and {interval}")
        if interval >= cfg.steps:
            raise TrainError(f"--pbt-interval {interval} leaves no exploit within --steps {cfg.steps}; "
                             "choose an interval below the steps")
        cfg = dataclasses.replace(cfg, checkpoint_every=interval)
        folder = new_pbt_dir(out, cfg, population).resolve()
        (folder / "pbt").mkdir(parents=True)
        (folder / "pbt.json").write_text(json.dumps({"config": cfg.to_dict(), "population": population,
                                                     "interval": interval}, indent=2))
    space = mutation_space(cfg.algo, cfg.agent_config)
    # a local population trains side by side, time-shared when it outnumbers the cores:
    # synchronous PBT would otherwise pause and restart trials at every interval
    import os

    with ray_session(address, num_cpus=None if address else max(os.cpu_count() or 1, population)):
        grid = _fit(cfg, population, interval, space, folder, resume is not None, concurrent)
    _finish(grid, folder, cfg, space)
    return folder


def _fit(cfg, population, interval, space, folder, resume, concurrent):
    from ray import tune
    from ray.tune.search import BasicVariantGenerator

    from eval.scale.pbt_scheduler import ResumablePBT
    from eval.scale.raysession import refuse_old_layout

    path = folder / "pbt" / "tune" / "pbt"
    random.seed(cfg.seed)  # PBT's explore draws from `random` in this process
    np.random.seed(cfg.seed)
    # Tuner.restore brings back this scheduler as it was at the start (Ray saves no
    # scheduler state): ResumablePBT rebuilds it from the restored trials (eval/scale/pbt_scheduler.py)
    scheduler = ResumablePBT(
        time_attr="env_steps", metric="mean_return", mode="max", perturbation_interval=interval,
        hyperparam_mutations=space, quantile_fraction=0.25, resample_probability=0.25, synch=True)
    if resume and tune.Tuner.can_restore(str(path)):
        refuse_old_layout(path)
        tuner = tune.Tuner.restore(str(path), _pbt_trial, resume_unfinished=True, resume_errored=True)
    else:
        tuner = tune.Tuner(
            _pbt_trial,
            param_space={"train": cfg.to_dict(), "pbt_dir": str(folder / "pbt"),
                         **{k: tune.choice(v) for k, v in space.items()}},
            tune_config=tune.TuneConfig(scheduler=scheduler, num_samples=population, reuse_actors=True,
                                        max_concurrent_trials=concurrent,
                                        trial_name_creator=lambda t: t.trial_id,
                                        trial_dirname_creator=lambda t: t.trial_id,
                                        search_alg=BasicVariantGenerator(random_state=cfg.seed)),
            run_config=tune.RunConfig(name="pbt", storage_path=str(folder / "pbt" / "tune"), verbose=0,
                                      checkpoint_config=tune.CheckpointConfig(num_to_keep=4),
                                      failure_config=tune.FailureConfig(max_failures=0)),
        )
    return tuner.fit()


def _finish(grid, folder: Path, cfg: TrainConfig, space: dict) -> None:
    """Lineage table and plot, trials table, and the best trial exported as the run folder."""
    import pandas as pd

    failed = [f"{r.path}: {type(r.error).__name__}" for r in grid if r.error is not None]
    if failed:
        raise TrainError(f"{len(failed)} PBT trial(s) failed: {'; '.join(failed)}")
    results = list(grid)
    if any((r.metrics or {}).get("env_steps", 0) < cfg.steps or r.checkpoint is None for r in results):
        raise TrainError(f"PBT interrupted before every trial finished; continue with: "
                         f"cosim train --resume {folder}")
    rows = [{"trial": Path(r.path).name, "env_steps": r.metrics["env_steps"],
             "mean_return": r.metrics["mean_return"],
             **{k: r.config[k] for k in space}} for r in results]
    pd.DataFrame(rows).to_csv(folder / "trials.csv", index=False)
    lineage = write_lineage(folder)
    plot_lineage(folder, lineage, next(iter(space)))
    best = max(results, key=lambda r: r.metrics["mean_return"])
    for item in Path(best.checkpoint.path).iterdir():
        if item.name == "run.lock":
            continue
        dest = folder / item.name
        if item.is_dir():
            shutil.rmtree(dest, ignore_errors=True)
            shutil.copytree(item, dest)
        else:
            shutil.copy2(item, dest)
    log.info("PBT best trial %s (mean return %.2f) exported to %s", best.metrics.get("trial_id"),
             best.metrics["mean_return"], folder)


def write_lineage(folder: Path):
    """``lineage.csv`` from the exploit records: one row per exploit and hyperparameter."""
    import pandas as pd

    rows = []
    for path in sorted((folder / "pbt" / "exploits").glob("*.json")):
        e = json.loads(path.read_text())
        for name, new in e["new_hyper"].items():
            donor = e["donor_hyper"].get(name)
            rows.append({"env_steps": e["env_steps"], "trial": e["trial"], "donor": e["donor"],
                         "parameter": name, "donor_value": donor, "new_value": new,
                         "previous_value": (e["previous_hyper"] or {}).get(name),
                         "perturbed": new != donor,
                         "donor_weights_sha256": e["donor_weights_sha256"],
                         "resumed_weights_sha256": e["resumed_weights_sha256"]})
    cols = ["env_steps", "trial", "donor", "parameter", "donor_value", "new_value", "previous_value",
            "perturbed", "donor_weights_sha256", "resumed_weights_sha256"]
    table = pd.DataFrame(rows, columns=cols)
    table.to_csv(folder / "lineage.csv", index=False)
    return table


def _histories(folder: Path) -> dict[str, list[dict]]:
    """Each trial's reports by step; a step reported twice (trained again after a resume,
    from the checkpoint before it) counts with its last report."""
    out = {}
    for path in sorted((folder / "pbt" / "history").glob("*.jsonl")):
        by_step = {}
        for line in path.read_text().splitlines():
            if line.strip():
                point = json.loads(line)
                by_step[point["env_steps"]] = point
        out[path.stem] = [by_step[k] for k in sorted(by_step)]
    return out


def plot_lineage(folder: Path, lineage, lr_field: str) -> Path:
    """Return per trial against steps, exploits as arrows from donor to clone; and each
    trial's ``lr_field`` (the first mutated hyperparameter) over steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    hist = _histories(folder)
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    colors = {t: f"C{i % 10}" for i, t in enumerate(sorted(hist))}
    for trial, points in hist.items():
        points = sorted(points, key=lambda p: p["env_steps"])
        steps = [p["env_steps"] for p in points]
        top.plot(steps, [p["mean_return"] if np.isfinite(p["mean_return"]) else np.nan for p in points],
                 "o-", color=colors[trial], ms=3, lw=1, label=trial)
        bottom.step(steps, [p["hyper"][lr_field] for p in points], where="pre", color=colors[trial])
    for e in lineage.drop_duplicates(["env_steps", "trial"]).itertuples():
        donor = {p["env_steps"]: p["mean_return"] for p in hist.get(e.donor, [])}.get(e.env_steps)
        if donor is not None and np.isfinite(donor):
            top.plot([e.env_steps], [donor], marker="*", ms=11, color=colors.get(e.trial, "k"),
                     markeredgecolor="k")
    top.set_ylabel("mean episodic return")
    top.set_title(f"PBT lineage: {len(lineage.drop_duplicates(['env_steps', 'trial']))} exploits "
                  "(star: a trial cloned the donor's checkpoint at that step)")
    top.grid(alpha=0.3)
    top.legend(fontsize=7, ncol=2)
    bottom.set_yscale("log" if "learning_rate" in lr_field else "linear")
    bottom.set_ylabel(lr_field)
    bottom.set_xlabel("environment steps")
    bottom.grid(alpha=0.3)
    fig.tight_layout()
    path = folder / "lineage.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
