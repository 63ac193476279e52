"""`cosim train --envs/--device/--torch-threads/--frame-stack/--collisions`: recorded in the
config, bad values refused."""

import pytest

from agents.base import resolve_device
from eval.training.train import TrainError, make_config


def test_envs_device_and_threads_are_part_of_the_config():
    cfg = make_config("ppo", "env_1", "smoke", envs=2, device="cpu", torch_threads=1)
    assert (cfg.envs, cfg.device, cfg.torch_threads) == (2, "cpu", 1)
    assert {"envs": 2, "device": "cpu", "torch_threads": 1}.items() <= cfg.to_dict().items()
    assert make_config("dqn", "env_1", "smoke").envs == 1  # the default: one env, in process


def test_a3c_and_impala_take_envs_and_default_to_the_presets_workers():
    from eval.training.presets import load_presets

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
    ({"algo": "ppo", "collisions": "stop"}, "--collisions must be event or step or end"),
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
    from eval.training.train import make_env

    assert make_config("ppo", "env_1", "smoke").frame_stack == 4  # the paper's released scripts' stack
    assert make_config("ppo", "env_1", "smoke", frame_stack=1).frame_stack == 1  # its text's single frame
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

    import eval.training.config
    from eval.training.presets import load_presets

    presets = dict(load_presets())
    presets["quick"] = dataclasses.replace(presets["quick"], envs=2, frame_stack=2)
    monkeypatch.setattr(eval.training.config, "load_presets", lambda: presets)
    cfg = make_config("ppo", "env_1", "quick")
    assert (cfg.envs, cfg.frame_stack) == (2, 2)
    assert make_config("a3c", "env_1", "quick").frame_stack == 2
    assert (make_config("ppo", "env_1", "quick", envs=1, frame_stack=1).envs, cfg.preset) == (1, "quick")


def _ram(cfg) -> list[tuple[bool, bool, float]]:
    """Drive the training env's ac_0 full throttle into a car placed 14 m ahead: per step
    (collision, terminated, reward) until the episode ends or 40 steps pass."""
    import numpy as np

    from eval.training.train import make_env

    env = make_env(cfg.to_dict())
    try:
        env.reset(seed=0)
        x, y, h, _ = env.world.ac_state("ac_0")
        env.world.bridge.place_car("target", x + 14 * np.cos(h), y + 14 * np.sin(h), h, "st_e")
        out = []
        for _ in range(40):
            _, rew, term, trunc, info = env.step({"ac_0": np.array([1.0, 0.0], np.float32)})
            out.append((bool(info["ac_0"]["collision_vehicle"]), bool(term["ac_0"]), float(rew["ac_0"])))
            if term["ac_0"] or trunc["ac_0"]:
                break
        return out
    finally:
        env.close()


def test_collisions_continue_trains_under_the_test_rule():
    """The default (`--collisions continue`): the AC's training episode goes on after it hits a
    car and every contact step is charged, as in the test, and a car driving on leaves the
    contact (cars are not solid: docs/task.md, "Collision rule"); `--collisions end` ends it at
    the first hit (the paper's)."""
    paper = make_config("ddpg", "env_1", "smoke", agents=1, collisions="end")
    assert paper.collisions_end_episode and paper.to_dict()["collisions_end_episode"] is True
    ended = _ram(paper)
    assert ended[-1][:2] == (True, True) and sum(hit for hit, _, _ in ended) == 1
    cfg = make_config("ddpg", "env_1", "smoke", agents=1)
    assert cfg.to_dict()["collisions_end_episode"] is False
    going = _ram(cfg)
    first = next(i for i, (hit, _, _) in enumerate(going) if hit)
    assert first == len(ended) - 1  # the same world up to the hit
    assert len(going) == 40 and not any(term for _, term, _ in going)
    contact = [rew for hit, _, rew in going[first:] if hit]
    assert len(contact) >= 2 and all(r < 0 for r in contact)  # charged again while in contact
    assert not going[-1][0]  # driving on, it has left the contact before the 40th step


def test_a_continue_run_config_reads_back_and_a_bad_flag_is_refused(tmp_path):
    """config.yaml of a `--collisions step` run loads again (resume, tests, --runs); a
    value that is not true/false is refused naming the key."""
    import yaml

    from eval.training.runfolder import load_run_config

    cfg = make_config("dqn", "env_1", "smoke", agents=1, collisions="step")
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(cfg.to_dict()))
    assert load_run_config(tmp_path).collisions_end_episode is False
    (tmp_path / "config.yaml").write_text(yaml.safe_dump({**cfg.to_dict(), "collisions_end_episode": "no"}))
    with pytest.raises(TrainError, match="'collisions_end_episode' must be bool"):
        load_run_config(tmp_path)
    (tmp_path / "config.yaml").write_text(yaml.safe_dump({**cfg.to_dict(), "agents": True}))
    with pytest.raises(TrainError, match="'agents' must be int"):
        load_run_config(tmp_path)


def test_cosim_train_collisions_step_reaches_the_run_config(tmp_path):
    import yaml

    from eval.cli import main

    assert main(["train", "--algo", "dqn", "--preset", "smoke", "--agents", "1", "--steps", "4",
                 "--collisions", "step", "--out", str(tmp_path), "--quiet"]) == 0
    (run,) = tmp_path.iterdir()
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["collisions_end_episode"] is False and config["collision_charge"] == "step"


def test_share_params_trains_one_network_for_every_ac_and_resumes_it(tmp_path):
    import torch
    import yaml

    import agents
    from agents.shared import shared_core
    from eval.training.train import train
    from eval.training.trainer import _load_or_build, make_env

    cfg = make_config("dqn", "env_1", "smoke", agents=2, steps=40, share_params=True,
                      validation_episodes=0)
    run = train(cfg, tmp_path, quiet=True, progress=False, keep="all")
    assert yaml.safe_load((run / "config.yaml").read_text())["share_params"] is True
    latest = [agents.load(run / "checkpoints" / f"ac_{k}" / "latest.pt") for k in range(2)]
    for key, tensor in latest[1].q_network.state_dict().items():  # every AC's file: the one network
        assert torch.equal(tensor, latest[0].q_network.state_dict()[key]), key
    assert latest[0].steps == 2 * 40  # the one learner saw both ACs' transitions
    assert agents.load(run / "checkpoints" / "ac_1" / "best.pt").algo == "dqn"
    env = make_env(cfg)
    try:  # resuming builds one core from ac_0's latest.pt and shares it again
        slots = _load_or_build(cfg, run, True, env.observation_space("ac_0"), env.action_space("ac_0"))
    finally:
        env.close()
    core = shared_core(slots)
    assert core is not None and core.steps == 80 and list(slots) == ["ac_0", "ac_1"]


def test_share_params_is_refused_for_a3c_and_impala():
    for algo in ("a3c", "impala"):
        with pytest.raises(TrainError, match="--share-params is for ppo, dqn, ddpg, td3"):
            make_config(algo, "env_1", "smoke", share_params=True)
    assert make_config("td3", "env_1", "smoke").share_params is False  # the paper's: one network per AC


def test_init_from_warm_starts_each_ac_from_a_run_and_is_recorded(tmp_path, capsys):
    """`cosim train --init-from RUN`: every AC starts from the source run's ac_k/best.pt (ac_0's
    where the source has fewer ACs), shared or not; config.yaml records the absolute path;
    a path with no checkpoint, another --obs and --algo all are refused in one line."""
    import torch
    import yaml

    import agents
    from eval.cli import main
    from eval.training.train import train
    from eval.training.trainer import _load_or_build, make_env

    source = train(make_config("dqn", "env_1", "smoke", agents=1, steps=40, validation_episodes=0),
                   tmp_path / "src", quiet=True, progress=False, keep="best")
    best = agents.load(source / "checkpoints" / "ac_0" / "best.pt")
    for share in (False, True):
        cfg = make_config("dqn", "env_1", "smoke", agents=2, steps=40, share_params=share,
                          init_from=source)
        assert cfg.init_from == str(source.resolve())
        env = make_env(cfg)
        try:
            slots = _load_or_build(cfg, tmp_path, False, env.observation_space("ac_0"), env.action_space("ac_0"))
        finally:
            env.close()
        for aid in ("ac_0", "ac_1"):
            for key, tensor in best.q_network.state_dict().items():
                assert torch.equal(slots[aid].q_network.state_dict()[key], tensor), (share, aid, key)
    capsys.readouterr()
    out = tmp_path / "runs"
    assert main(["train", "--algo", "dqn", "--preset", "smoke", "--agents", "1", "--steps", "40",
                 "--init-from", str(source), "--out", str(out), "--quiet"]) == 0
    run = next(out.iterdir())
    assert yaml.safe_load((run / "config.yaml").read_text())["init_from"] == str(source.resolve())
    for args, match in (([str(tmp_path / "nowhere")], "not a checkpoint file nor a run folder"),
                        ([str(source), "--obs", "nav"], "same --obs"),
                        ([str(source), "--algo", "all"], "choose it with --algo")):
        capsys.readouterr()
        cmd = ["train", "--algo", "dqn", "--preset", "smoke", "--agents", "1", "--steps", "40",
               "--out", str(out), "--quiet", "--init-from"] + args
        assert main(cmd) == 2, args
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and match in err, err
        assert [p.name for p in out.iterdir()] == [run.name], "a refused run leaves no folder"


def test_demo_steps_fill_the_replays_before_training_and_again_on_resume(tmp_path, capsys):
    """`--demo-steps 60 --demo-updates 5`: the autopilot drives whole episodes first, every AC's
    transitions go to its replay uncounted (the agents' steps are the budget's alone), DQN
    pre-trains once; a resumed run drives them again (the replay is not saved) without
    pre-training; demos.json records each phase."""
    import json

    import agents
    from eval.training.train import train

    cfg = make_config("dqn", "env_1", "smoke", agents=2, steps=40, validation_episodes=0, demo_steps=60,
                      demo_updates=5, hyper={"demo_margin": "0.8"})
    assert (cfg.demo_steps, cfg.demo_updates, cfg.agent_config.demo_margin) == (60, 5, 0.8)
    run = train(cfg, tmp_path, quiet=True, progress=False)
    out = capsys.readouterr().out  # a --quiet run says what each phase did
    assert "[dqn env_1] demonstrations: " in out and "[dqn env_1] pre-training: 5 updates per network" in out
    phases = json.loads((run / "demos.json").read_text())
    assert len(phases) == 1 and phases[0]["env_steps"] >= 60 and phases[0]["episodes"] >= 1
    assert set(phases[0]["agents"]) == {"ac_0", "ac_1"}
    assert all(v["transitions"] > 40 for v in phases[0]["agents"].values())
    assert phases[0]["pretrain"]["updates"] == 5 and set(phases[0]["pretrain"]["metrics"]) == {"ac_0", "ac_1"}
    latest = agents.load(run / "checkpoints" / "ac_0" / "latest.pt")
    assert latest.steps <= 40 < phases[0]["agents"]["ac_0"]["transitions"] + latest.steps
    assert latest.gradient_updates >= 5
    train(cfg, resume=run, steps=60, quiet=True, progress=False)
    phases = json.loads((run / "demos.json").read_text())
    assert len(phases) == 2 and "pretrain" not in phases[1]
    assert agents.load(run / "checkpoints" / "ac_0" / "latest.pt").steps <= 60


def test_td3_takes_the_continuous_autopilots_demonstrations(tmp_path):
    import json

    from eval.training.train import train

    cfg = make_config("td3", "env_1", "smoke", agents=1, steps=20, validation_episodes=0, demo_steps=30,
                      demo_updates=4, hyper={"demo_bc": "2.5"})
    run = train(cfg, tmp_path, quiet=True, progress=False)
    (phase,) = json.loads((run / "demos.json").read_text())
    assert phase["agents"]["ac_0"]["transitions"] >= 30 and phase["pretrain"]["updates"] == 4
    assert "losses/actor_loss" in phase["pretrain"]["metrics"]["ac_0"]  # policy_delay 2: the actor learned


@pytest.mark.parametrize(("algo", "kwargs", "match"), [
    ("ppo", {"demo_steps": 100}, "--demo-steps fills a replay buffer: dqn, ddpg, td3 only, not ppo"),
    ("dqn", {"demo_steps": -1}, "--demo-steps must be >= 0 \\(0: off\\), got -1"),
    ("dqn", {"demo_updates": 10}, "--demo-updates pre-trains on the demonstrations: give them with --demo-steps"),
])
def test_bad_demonstration_options_are_refused(algo, kwargs, match):
    with pytest.raises(TrainError, match=match):
        make_config(algo, "env_1", "smoke", **kwargs)


def test_cosim_train_refuses_demonstrations_for_all_algorithms(tmp_path, capsys):
    from eval.cli import main

    assert main(["train", "--algo", "all", "--preset", "smoke", "--demo-steps", "60", "--out",
                 str(tmp_path), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "choose it with --algo dqn, ddpg or td3" in err
    assert not any(tmp_path.iterdir())
