"""The frozen perception encoder end to end (eval/training/encoder.py, eval/cli/encoder.py;
docs/task.md, "The frozen perception encoder"): `cosim encoder train` builds a small one from the
simulator here; `cosim train --encoder` trains the heads of a discrete and a continuous algorithm
on its features with their unchanged code (replay of features, the encoder untouched) and records
its hash; `cosim test` drives such a checkpoint on the features of its own frames and refuses it
with another encoder file, as a resume does."""

import shutil

import numpy as np
import pytest
import torch
import yaml

import agents
from agents.encoder import file_sha256, load_encoder
from agents.registry import get_agent_class
from cosim.state import STATE_DIM, STATE_LAYOUT
from eval.cli import main
from eval.training.config import TrainError, make_config
from eval.training.encoder import (
    LABEL_GROUPS,
    PerturbedAutopilot,
    group_errors,
    label_names,
    label_weights,
)


@pytest.fixture(scope="module")
def encoder(tmp_path_factory):
    """A tiny encoder: 40 frames of two ACs on Straight, one epoch (seconds)."""
    path = tmp_path_factory.mktemp("encoder") / "enc.pt"
    assert main(["encoder", "train", "--out", str(path), "--frames", "40", "--epochs", "1", "--envs", "env_1",
                 "--agents", "2", "--horizon", "30", "--held-out", "0.25", "--quiet"]) == 0
    return path


@pytest.fixture(scope="module")
def other(encoder, tmp_path_factory):
    """Another encoder file (the same weights, other bytes: another hash)."""
    payload = torch.load(encoder, weights_only=True)
    payload["info"]["note"] = "rebuilt"
    path = tmp_path_factory.mktemp("other") / "other.pt"
    torch.save(payload, path)
    return path


@pytest.fixture(scope="module")
def runs(encoder, tmp_path_factory):
    """`cosim train --encoder` of DQN and TD3 (smoke, one AC, 40 steps); the agents in memory
    at their last checkpoint (algo -> agent) beside the runs folder."""
    from eval.training.runlog import RunLog

    out = tmp_path_factory.mktemp("runs")
    seen = {}
    save = RunLog.checkpoint

    def checkpoint(self, agent_map, env_step, extra_time=None):
        seen[self.cfg.algo] = agent_map["ac_0"]
        return save(self, agent_map, env_step, extra_time)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(RunLog, "checkpoint", checkpoint)
        for algo in ("dqn", "td3"):
            assert main(["train", "--algo", algo, "--preset", "smoke", "--env", "env_1", "--agents", "1",
                         "--steps", "40", "--encoder", str(encoder), "--out", str(out), "--quiet"]) == 0
    return out, seen


def test_cosim_encoder_train_writes_an_encoder_of_the_state_labels_with_its_held_out_error(encoder, capsys):
    enc = load_encoder(encoder)
    info = enc.info
    assert enc.labels == tuple(label_names()) and len(enc.labels) == STATE_DIM and enc.obs == "image"
    assert info["frames"] == 40 and info["held_out_frames"] == 10 and info["envs"] == ["env_1"]
    assert set(info["held_out_error"]) == set(LABEL_GROUPS)
    assert info["data_bytes"] >= 40 * 84 * 84 * 3 and len(info["train_loss"]) == 1
    features = enc.encode(np.zeros((84, 84, 3), np.uint8))
    assert features.shape == (512,) and features.dtype == np.float32


def test_the_labels_count_what_a_frame_can_show_and_the_errors_compare_with_the_mean():
    labels = np.zeros((2, STATE_DIM), np.float32)
    veh = STATE_LAYOUT["vehicles"].start
    labels[0, veh:veh + 5] = (1.0, 0.2, -0.1, 0.3, 0.0)  # slot 0 of frame 0 holds a car; frame 1 none
    w = label_weights(labels)
    assert not w[:, STATE_LAYOUT["control"]].any()  # the previous action is not in a frame
    assert w[0, veh:veh + 5].tolist() == [1, 1, 1, 1, 1] and w[1, veh:veh + 5].tolist() == [1, 0, 0, 0, 0]
    rng = np.random.default_rng(0)
    y = rng.normal(size=(50, STATE_DIM)).astype(np.float32)
    mean, std = y.mean(0), y.std(0)
    exact = group_errors(y, y, mean, std)
    by_mean = group_errors(np.broadcast_to(mean, y.shape), y, mean, std)
    assert all(e["mse"] == 0 and e["ratio"] == 0 for e in exact.values())
    assert all(abs(e["ratio"] - 1) < 1e-3 for e in by_mean.values())


def test_the_perturbed_autopilot_adds_noise_and_holds_random_excursions(monkeypatch):
    import cosim.controller

    class Pilot:
        def __init__(self, world, ac):
            self.calls = 0

        def act(self):
            self.calls += 1
            return np.array([0.5, 0.0])

    monkeypatch.setattr(cosim.controller, "Autopilot", Pilot)
    noisy = PerturbedAutopilot(None, "ac_0", np.random.default_rng(0), rate=0.0)
    actions = np.array([noisy.act() for _ in range(50)])
    assert np.all(np.abs(actions) <= 1) and actions.std(axis=0).min() > 0.05 and noisy.pilot.calls == 50
    held = PerturbedAutopilot(None, "ac_0", np.random.default_rng(1), rate=1.0)
    first = [held.act() for _ in range(5)]  # an excursion holds >= 5 steps
    assert all(np.array_equal(a, first[0]) for a in first) and not np.allclose(first[0], [0.5, 0.0])
    assert held.pilot.calls == 5  # the autopilot is asked every step all the same


def test_train_with_an_encoder_learns_heads_on_its_features_and_records_its_hash(encoder, runs):
    out, seen = runs
    sha = file_sha256(encoder)
    for algo, action_space in (("dqn", "Discrete"), ("td3", "Box")):
        (run,) = out.glob(f"env_1__{algo}__*")
        cfg = yaml.safe_load((run / "config.yaml").read_text())
        assert cfg["encoder"] == str(encoder.resolve()) and cfg["encoder_sha256"] == sha
        manifest = yaml.safe_load((run / "manifest.json").read_text())
        assert manifest["encoder"] == {"path": str(encoder.resolve()), "sha256": sha}
        best = agents.load(run / "checkpoints" / "ac_0" / "best.pt")
        assert best.observation_space.shape == (512 * cfg["frame_stack"],) and best.observation_space.dtype == np.float32
        assert tuple(best.config.hidden) == (256, 256) and type(best.action_space).__name__ == action_space
        agent = seen[algo]
        assert not any(isinstance(m, torch.nn.Conv2d) for net in agent.networks.values() for m in net.modules())
        # the replay holds the 4 stacked feature vectors of each transition, float32, not frames
        assert agent.buffer.obs.dtype == np.float32 and agent.buffer.obs.shape[1:] == (2048,) and len(agent.buffer)
        fresh = [get_agent_class(algo).from_spaces(best.observation_space, best.action_space, agent.config, seed=0)
                 for _ in range(2)]
        trained, start, again = (a.state_dict()["networks"] for a in (agent, *fresh))
        assert all(torch.equal(start[n][k], again[n][k]) for n in start for k in start[n])  # seeded init
        assert any(not torch.equal(trained[n][k], start[n][k]) for n in trained for k in trained[n]), algo
    from eval.training.encoder import _load

    used = _load(str(encoder.resolve()), sha, None)  # the frozen encoder the training envs encoded with
    assert file_sha256(encoder) == sha and not any(p.requires_grad for p in used.net.parameters())
    reloaded = load_encoder(encoder).net.state_dict()
    assert all(torch.equal(v, reloaded[k]) for k, v in used.net.state_dict().items())  # it did not learn


def test_an_encoder_takes_camera_frames_only(encoder):
    for obs in ("nav", "state"):
        with pytest.raises(TrainError, match=f"--encoder encodes camera frames; --obs {obs} .*: use --obs image"):
            make_config("dqn", preset="smoke", obs=obs, encoder=str(encoder))
    with pytest.raises(TrainError, match="no such file; build one with `cosim encoder train"):
        make_config("dqn", preset="smoke", encoder=str(encoder.with_name("missing.pt")))


def test_cosim_test_drives_on_the_runs_encoder_and_refuses_another(encoder, other, runs, tmp_path, capsys):
    from eval.testing.loading import drive, load_for_slot
    from eval.testing.protocol import ProtocolError
    from eval.testing.rollout import EncodedPolicy

    out, _ = runs
    (run,) = out.glob("env_1__dqn__*")
    ckpt = run / "checkpoints" / "ac_0" / "best.pt"
    agent = load_for_slot(ckpt, "dqn")
    policy = drive(agent)
    assert isinstance(policy, EncodedPolicy) and policy.frame_stack == 4
    frame = np.random.default_rng(0).integers(0, 256, (84, 84, 3), dtype=np.uint8)
    features = load_encoder(encoder).encode(frame)
    policy.reset()
    assert policy.act(frame) == agent.act(np.concatenate([features] * 4), deterministic=True)
    test = ["test", "--algos", "dqn", "--envs", "env_1", "--episodes", "1", "--steps", "3", "--scenario", "1",
            "--references", "none", "--no-replays", "--runs", str(out), "--out", str(tmp_path / "reports"), "--quiet"]
    capsys.readouterr()
    assert main([*test, "--encoder", str(other)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"was trained on the frozen encoder {encoder.resolve()}" in err
    assert f"not on {other}" in err and "give `cosim test --encoder FILE` with the file its run was trained on" in err
    copy = tmp_path / run.name  # the run's encoder file rebuilt (another hash at the recorded path): resume refuses
    shutil.copytree(run, copy)
    cfg = yaml.safe_load((copy / "config.yaml").read_text())
    cfg["encoder"] = str(other)
    (copy / "config.yaml").write_text(yaml.safe_dump(cfg))
    assert main(["train", "--resume", str(copy), "--quiet"]) == 2
    assert "it was recorded with: the file was rebuilt or replaced" in capsys.readouterr().err
    with pytest.raises(ProtocolError, match="was trained on the frozen encoder"):
        load_for_slot(copy / "checkpoints" / "ac_0" / "best.pt", "dqn")
    shutil.copy(ckpt, tmp_path / "alone.pt")  # out of its run folder: no record of its encoder
    with pytest.raises(ProtocolError, match=r"not the state track's \(65,\): a run trained with --encoder"):
        load_for_slot(tmp_path / "alone.pt", "dqn")
