"""`cosim train --envs/--device/--torch-threads`: recorded in the config, bad values refused."""

import pytest

from agents.base import resolve_device
from eval.train import TrainError, make_config


def test_envs_device_and_threads_are_part_of_the_config():
    cfg = make_config("ppo", "env_1", "smoke", envs=2, device="cpu", torch_threads=1)
    assert (cfg.envs, cfg.device, cfg.torch_threads) == (2, "cpu", 1)
    assert {"envs": 2, "device": "cpu", "torch_threads": 1}.items() <= cfg.to_dict().items()
    assert make_config("dqn", "env_1", "smoke").envs == 1  # the default: one env, in process


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"algo": "ppo", "envs": 0}, "--envs"),
    ({"algo": "a3c", "envs": 2}, "one environment per worker"),
    ({"algo": "td3", "device": "tpu"}, "--device"),
    ({"algo": "ppo", "torch_threads": -1}, "--torch-threads"),
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
