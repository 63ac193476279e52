"""`cosim train --envs/--device/--torch-threads/--frame-stack`: recorded in the config, bad
values refused."""

import pytest

from agents.base import resolve_device
from eval.train import TrainError, make_config


def test_envs_device_and_threads_are_part_of_the_config():
    cfg = make_config("ppo", "env_1", "smoke", envs=2, device="cpu", torch_threads=1)
    assert (cfg.envs, cfg.device, cfg.torch_threads) == (2, "cpu", 1)
    assert {"envs": 2, "device": "cpu", "torch_threads": 1}.items() <= cfg.to_dict().items()
    assert make_config("dqn", "env_1", "smoke").envs == 1  # the default: one env, in process


def test_a3c_and_impala_take_envs_and_default_to_the_presets_workers():
    from eval.presets import load_presets

    for algo in ("a3c", "impala"):
        assert make_config(algo, "env_1", "smoke", envs=3).envs == 3
        for preset in ("smoke", "quick"):
            assert make_config(algo, "env_1", preset).envs == load_presets()[preset].workers


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"algo": "ppo", "envs": 0}, "--envs"),
    ({"algo": "a3c", "envs": 0}, "--envs"),
    ({"algo": "td3", "device": "tpu"}, "--device"),
    ({"algo": "ppo", "torch_threads": -1}, "--torch-threads"),
    ({"algo": "dqn", "frame_stack": 0}, "--frame-stack must be >= 1"),
])
def test_bad_values_are_refused_naming_the_option(kwargs, match):
    algo = kwargs.pop("algo")
    with pytest.raises(TrainError, match=match):
        make_config(algo, "env_1", "smoke", **kwargs)


def test_auto_device_falls_back_to_cpu_without_cuda(monkeypatch):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == "cpu" and resolve_device("cpu") == "cpu"
    with pytest.raises(ValueError, match="no CUDA device"):
        resolve_device("cuda")


def test_frame_stack_is_part_of_the_config_and_shapes_the_training_env():
    from eval.train import make_env

    assert make_config("ppo", "env_1", "smoke").frame_stack == 1  # the paper's single frame
    cfg = make_config("td3", "env_1", "smoke", frame_stack=3)
    assert cfg.to_dict()["frame_stack"] == 3
    env = make_env(cfg.to_dict())
    try:
        assert env.observation_space("ac_0").shape == (84, 84, 9)
        obs, _ = env.reset(seed=0)
        assert obs["ac_0"].shape == (84, 84, 9)
        assert all((obs["ac_0"][..., 3 * j: 3 * j + 3] == obs["ac_0"][..., :3]).all() for j in range(3))
    finally:
        env.close()


def test_the_preset_gives_envs_and_frame_stack_unless_the_command_does(monkeypatch):
    import dataclasses

    import eval.config
    from eval.presets import load_presets

    presets = dict(load_presets())
    presets["quick"] = dataclasses.replace(presets["quick"], envs=2, frame_stack=2)
    monkeypatch.setattr(eval.config, "load_presets", lambda: presets)
    cfg = make_config("ppo", "env_1", "quick")
    assert (cfg.envs, cfg.frame_stack) == (2, 2)
    assert make_config("a3c", "env_1", "quick").frame_stack == 2
    assert (make_config("ppo", "env_1", "quick", envs=1, frame_stack=1).envs, cfg.preset) == (1, "quick")
