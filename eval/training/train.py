"""Training runs: the public face of the training layer (``cosim train``).

The layer, one concern per module:

    agents/registry.py    the algorithm catalogue: name, class, action kind, sync/async loop,
                          policy kind
    eval/training/presets.py       run presets (smoke, quick, standard, paper) from eval/training/hyperparams/*.yaml
    eval/training/options.py       RunOptions: a run's options, declared once (flags, checks, report keys)
    eval/training/config.py        TrainConfig, resolve (options -> config), make_config, --set typing
    eval/training/runfolder.py     the run folder: layout, config.yaml, manifest, lock, resume recovery
    eval/training/runlog.py        episodes.csv (columns from the event and reward-term catalogues),
                          TensorBoard, checkpoints
    eval/training/trainer.py       train(): the sync (vector env) and async (worker) paths, env factory
    eval/training/validation.py    held-out validation episodes at each checkpoint that pick best.pt
    eval/training/plots.py         the convergence plot

This module re-exports their public names, so ``from eval.training.train import train,
make_config`` keeps working.
"""

from eval.training.config import (
    ALGORITHMS,
    ASYNC_ALGOS,
    CONTINUOUS_ALGOS,
    DISCRETE_ALGOS,
    TrainConfig,
    TrainError,
    make_config,
    parse_hyper,
    parse_set,
    resolve,
)
from eval.training.plots import plot_convergence
from eval.training.presets import TrainPreset, load_presets
from eval.training.runfolder import (
    RunLock,
    atomic_write,
    load_run_config,
    manifest,
    new_run_dir,
    read_state,
    recover_checkpoints,
)
from eval.training.runlog import EPISODE_FIELDS, RunLog
from eval.training.trainer import make_env, train

__all__ = [
    "ALGORITHMS", "ASYNC_ALGOS", "CONTINUOUS_ALGOS", "DISCRETE_ALGOS", "EPISODE_FIELDS", "RunLock",
    "RunLog", "TrainConfig", "TrainError", "TrainPreset", "atomic_write", "load_presets",
    "load_run_config", "make_config", "make_env", "manifest", "new_run_dir", "parse_hyper",
    "parse_set", "plot_convergence", "read_state", "recover_checkpoints", "resolve", "train",
]
