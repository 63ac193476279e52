"""The learners' device path without a GPU (issue 29): `cosim train --device cuda` runs
through the same code a GPU machine runs, with the CUDA device stood in for by a CPU
device of its own name, so plumbing that drops the device (an agent built on the
default, a tensor or optimizer state left behind) fails here and not first on a rented
GPU. And `bench/train_throughput.py --device cuda` says in one line why it cannot run.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

# A CPU device that is not the default "cpu": an agent built without the resolved device
# (torch.device("cpu")) differs from one built with it (torch.device("cpu", 0))
FAKE_CUDA = "cpu:0"


def _tensors(agent):
    """(name, tensor) of every parameter, buffer and optimizer state tensor of an agent."""
    for net_name, net in agent.networks.items():
        for name, t in [*net.named_parameters(), *net.named_buffers()]:
            yield f"{net_name}.{name}", t
    for opt_name, opt in agent.optimizers.items():
        for i, state in enumerate(opt.state.values()):
            for key, value in state.items():
                if torch.is_tensor(value):
                    yield f"{opt_name}.state[{i}].{key}", value


@pytest.mark.parametrize("algo", ["ppo", "dqn", "ddpg", "td3"])
def test_device_cuda_reaches_every_learner_tensor_through_the_cli(algo, tmp_path, monkeypatch):
    import agents.base
    import eval.training.trainer as trainer
    from eval.cli import main

    asked, built = [], []
    real_resolve = agents.base.resolve_device

    def fake_resolve(name="auto"):  # the one place that checks for CUDA: a stand-in device
        asked.append(name)
        return FAKE_CUDA if name == "cuda" else real_resolve(name)

    real_build = trainer._load_or_build

    def recording_build(*args, **kwargs):
        out = real_build(*args, **kwargs)
        built.append(out)
        return out

    monkeypatch.setattr(agents.base, "resolve_device", fake_resolve)
    monkeypatch.setattr(trainer, "_load_or_build", recording_build)
    # 40 steps, one checkpoint (smoke: PPO's rollout 32, the others learn from step 32)
    code = main(["train", "--algo", algo, "--preset", "smoke", "--steps", "40", "--agents", "1", "--device", "cuda",
                 "--torch-threads", "1", "--out", str(tmp_path), "--quiet", "--keep", "all"])
    assert code == 0
    assert asked == ["cuda"]
    (run,) = tmp_path.iterdir()
    assert yaml.safe_load((run / "config.yaml").read_text())["device"] == "cuda"
    (agent_map,) = built
    for aid, agent in agent_map.items():
        assert agent.device == torch.device(FAKE_CUDA), (aid, agent.device)
        assert agent.generator.device.type == "cpu"
        assert agent.steps > 0 and any(opt.state for opt in agent.optimizers.values()), f"{aid} never learned"
        named = list(_tensors(agent))
        assert named
        wrong = [n for n, t in named if t.device.type != torch.device(FAKE_CUDA).type]
        assert not wrong, wrong[:5]


def test_train_throughput_with_device_cuda_and_no_gpu_fails_in_one_line():
    if torch.cuda.is_available():
        pytest.skip("a GPU is here: the benchmark would run")
    root = Path(__file__).resolve().parents[2]
    done = subprocess.run([sys.executable, str(root / "bench" / "train_throughput.py"), "--device", "cuda",
                           "--envs", "1", "4", "8", "16"], capture_output=True, text=True, timeout=300,
                          cwd=root)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "--device cuda" in lines[0] and "no CUDA device" in lines[0], done.stderr
    assert not done.stdout.strip()
