"""One hyperparameter from the command line to the optimiser (issue 26; docs/design.md, "One
hyperparameter from the command line to the optimiser"): the typed config the CLI layer builds
(``make_config``'s ``TrainConfig.agent_config``, a ``PPOConfig``) is the very object the
algorithm's constructor receives, nothing rebuilds it from a dict on the way, and the optimiser
holds the command line's value; the path the design doc lists is <= 5 hops of functions that exist.
"""

from __future__ import annotations

import pickle
import re
import subprocess
import sys
from pathlib import Path

import pytest

from agents import registry
from agents.configs import AgentConfig, PPOConfig
from eval.cli import main
from eval.training.config import TrainError
from eval.training.presets import load_presets

ROOT = Path(__file__).resolve().parents[2]


class _Stop(TrainError):
    """Ends the run once the agent is built (what follows is training, not the path); a
    TrainError, so ``cosim train`` reports it as one line and exits 2."""


def _spy_on_the_cli_layer(monkeypatch) -> tuple[list, list]:
    """Capture every TrainConfig ``cosim train`` builds, and every ``AgentConfig.from_dict`` call
    (the rebuild a typed -> dict -> typed round trip would need), in order, in ``events``."""
    import eval.training.train as train_module

    built, events = [], []
    resolve = train_module.resolve  # what make_config and cosim train resolve a run's options with

    def recording_resolve(*args, **kwargs):
        cfg = resolve(*args, **kwargs)
        built.append(cfg)
        events.append("make_config")
        return cfg

    from_dict = AgentConfig.from_dict.__func__

    def recording_from_dict(cls, values):
        events.append(f"from_dict {cls.__name__}")
        return from_dict(cls, values)

    monkeypatch.setattr(train_module, "resolve", recording_resolve)  # cmd_train imports it from here
    monkeypatch.setattr(AgentConfig, "from_dict", classmethod(recording_from_dict))
    return built, events


def test_set_learning_rate_reaches_ppos_optimiser_as_the_typed_config_make_config_built(tmp_path, monkeypatch):
    from agents.ppo import PPO

    built, events = _spy_on_the_cli_layer(monkeypatch)
    received = []
    init = PPO.__init__

    def capturing_init(self, observation_space, action_space, config=None, seed=0, device="cpu"):
        events.append("PPO.__init__")
        init(self, observation_space, action_space, config=config, seed=seed, device=device)
        received.append((config, self.optimizers["optimizer"].param_groups[0]["lr"]))
        raise _Stop

    monkeypatch.setattr(PPO, "__init__", capturing_init)
    assert main(["train", "--algo", "ppo", "--preset", "smoke", "--agents", "1", "--steps", "50",
                 "--set", "learning_rate=1.25e-4", "--validation-episodes", "0", "--out", str(tmp_path)]) == 2
    (cfg,) = built
    config, lr = received[0]
    assert type(cfg.agent_config) is PPOConfig and cfg.agent_config.learning_rate == 1.25e-4
    assert config is cfg.agent_config  # the same object: no dict on the way
    assert lr == 1.25e-4  # what torch.optim.Adam was given
    # the run preset's values are there too: its reward scale and hyperparams/ppo.yaml's changes
    smoke = load_presets()["smoke"]
    assert config.reward_scale == smoke.reward_scale and smoke.overrides["ppo"]
    assert all(getattr(config, k) == v for k, v in smoke.overrides["ppo"].items()), smoke.overrides["ppo"]
    # nothing rebuilt it from a dict in between (make_config itself builds the preset's config
    # from PPOConfig.PRESETS and hyperparams/ppo.yaml: from_dict before "make_config")
    assert events[events.index("make_config"):] == ["make_config", "PPO.__init__"], events


def test_the_async_algorithms_get_the_typed_config_as_it_is(tmp_path, monkeypatch):
    """A3C and IMPALA train on the same trainer path as PPO (one loop, agents.loop.run_loop):
    the agents it builds get the same object."""
    from agents.a3c import A3C

    built, events = _spy_on_the_cli_layer(monkeypatch)
    received = []
    init = A3C.__init__

    def capturing_init(self, observation_space, action_space, config=None, seed=0, device="cpu"):
        events.append("A3C.__init__")
        init(self, observation_space, action_space, config=config, seed=seed, device=device)
        received.append(config)
        raise _Stop

    monkeypatch.setattr(A3C, "__init__", capturing_init)
    assert main(["train", "--algo", "a3c", "--preset", "smoke", "--agents", "1", "--envs", "1", "--steps", "50",
                 "--set", "learning_rate=2e-4", "--validation-episodes", "0", "--out", str(tmp_path)]) == 2
    (cfg,) = built
    assert received[0] is cfg.agent_config and received[0].learning_rate == 2e-4
    assert type(received[0]) is registry.get_config_class("a3c")
    assert events[events.index("make_config"):] == ["make_config", "A3C.__init__"], events


def test_pbt_perturbs_the_typed_config_with_dataclasses_replace():
    from eval.scale.pbt import mutation_space, with_hyper
    from eval.training.train import make_config

    cfg = make_config("ppo", "env_1", "quick")
    space = mutation_space("ppo", cfg.agent_config)
    value = space["learning_rate"][0]
    changed = with_hyper(cfg, {"learning_rate": value, "ent_coef": space["ent_coef"][-1]})
    assert type(changed.agent_config) is PPOConfig and changed.agent_config.learning_rate == value
    assert changed.agent_config == cfg.agent_config.replace(learning_rate=value, ent_coef=space["ent_coef"][-1])
    with pytest.raises(ValueError, match="out of range"):  # validated again, as on the command line
        with_hyper(cfg, {"learning_rate": 2.0})


def test_each_algorithms_config_class_is_torch_free_and_the_agents_own():
    for algo in registry.ALGORITHMS:
        assert registry.get_config_class(algo) is registry.get_agent_class(algo).config_class
    probe = ("import pickle, sys; from eval.training.config import make_config; "
             "cfg = make_config('td3', hyper={'actor_learning_rate': '1e-4'}); "
             "pickle.loads(pickle.dumps(cfg)); "
             "assert 'torch' not in sys.modules, 'torch imported'; print(type(cfg.agent_config).__name__)")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120,
                         cwd=ROOT)
    assert out.returncode == 0 and out.stdout.strip() == "TD3Config", out.stderr[-2000:]


def test_a_config_read_back_from_its_dict_is_the_same_typed_config():
    """Serialisation (config.yaml, pbt.json, a Ray trial's config) is a mapping; reading it back
    builds the typed config once, equal to the one written."""
    from eval.training.config import TrainConfig, TrainError, make_config

    cfg = make_config("impala", hyper={"learning_rate": "3e-4"})
    data = cfg.to_dict()
    assert isinstance(data["agent_config"], dict)
    again = TrainConfig(**data)
    assert again == cfg and type(again.agent_config) is type(cfg.agent_config)
    assert pickle.loads(pickle.dumps(cfg)) == cfg
    with pytest.raises(TrainError, match="impala's config class is IMPALAConfig, got a PPOConfig"):
        TrainConfig(algo="impala", agent_config=PPOConfig())
    with pytest.raises(TrainError, match=r"'agent_config': unknown IMPALAConfig field\(s\) \['lr'\]"):
        TrainConfig(algo="impala", agent_config={"lr": 1e-3})


def test_the_design_doc_path_is_at_most_five_hops_of_real_functions():
    design = (ROOT / "docs" / "design.md").read_text()
    section = design.split("### One hyperparameter from the command line to the optimiser", 1)[1]
    section = section.split("\n## ", 1)[0].split("\n### ", 1)[0]
    hops = re.findall(r"^(\d+)\. `([^`]+\.py)` `([\w.]+)`", section, flags=re.MULTILINE)
    assert 1 <= len(hops) <= 5 and [int(n) for n, _, _ in hops] == list(range(1, len(hops) + 1)), hops
    for _, path, function in hops:
        source = (ROOT / path).read_text()
        assert re.search(rf"^\s*def {function.split('.')[-1]}\(", source, flags=re.MULTILINE), (path, function)


def test_pbts_explore_writes_the_perturbed_config_into_the_run_it_resumes(tmp_path):
    """``apply_hyper`` (before a PBT trial resumes a run): config.yaml, each checkpoint's config
    and its optimiser's learning rate get the typed config's values."""
    import gymnasium
    import numpy as np

    import agents
    from agents.ppo import PPO
    from eval.scale.pbt import apply_hyper, with_hyper
    from eval.training.runfolder import load_run_config
    from eval.training.train import make_config

    cfg = make_config("ppo", "env_1", "smoke")
    space = gymnasium.spaces.Box(-1.0, 1.0, (4,), np.float32)
    PPO.from_spaces(space, gymnasium.spaces.Discrete(9), cfg.agent_config).save(tmp_path / "checkpoints/ac_0/latest.pt")
    new = with_hyper(cfg, {"learning_rate": 5e-5, "ent_coef": 0.02})
    apply_hyper(tmp_path, new)
    assert load_run_config(tmp_path) == new
    loaded = agents.load(tmp_path / "checkpoints/ac_0/latest.pt")
    assert loaded.config == new.agent_config and type(loaded.config) is PPOConfig
    assert loaded.optimizers["optimizer"].param_groups[0]["lr"] == 5e-5


def test_an_exploit_applied_again_after_a_resume_keeps_its_first_record(tmp_path):
    """Ctrl-C before a clone reports leaves Tune's restore point at the donor's checkpoint:
    ``--resume`` applies the same exploit again, when the trial's own hyperparameters file
    already holds the new values. The record of the first application (its true
    ``previous_hyper``) must stay, not be rewritten (the cluster test's lineage check)."""
    import json

    import gymnasium
    import numpy as np

    from agents.ppo import PPO
    from eval.scale.pbt import _record_exploit
    from eval.training.train import make_config

    cfg = make_config("ppo", "env_1", "smoke")
    space = gymnasium.spaces.Box(-1.0, 1.0, (4,), np.float32)
    donor, run = tmp_path / "donor", tmp_path / "run"
    for folder in (donor, run):
        PPO.from_spaces(space, gymnasium.spaces.Discrete(9), cfg.agent_config).save(
            folder / "checkpoints/ac_0/latest.pt")
    meta = {"env_steps": 60, "trial": "t1", "hyper": {"learning_rate": 1e-4}}
    new, old = {"learning_rate": 2e-4}, {"learning_rate": 9e-4}
    _record_exploit(tmp_path / "pbt", "t0", meta, new, old, donor, run)
    (record,) = (tmp_path / "pbt" / "exploits").glob("*.json")
    assert record.name == "0000000060-t0.json"
    first = record.read_text()
    assert json.loads(first)["previous_hyper"] == old
    _record_exploit(tmp_path / "pbt", "t0", meta, new, new, donor, run)  # the resume's second application
    assert record.read_text() == first
    assert [p.name for p in (tmp_path / "pbt" / "exploits").iterdir()] == [record.name]
    # a later barrier is a new record
    _record_exploit(tmp_path / "pbt", "t0", {**meta, "env_steps": 120}, new, new, donor, run)
    assert len(list((tmp_path / "pbt" / "exploits").glob("*.json"))) == 2
