"""The test protocol: Scenario 1 and 2 on the real simulator, its metric table, checkpoint lookup
(the report written from the records: tests/eval/test_report.py)."""

import json

import numpy as np
import pandas as pd
import pytest
from gymnasium import spaces

from agents.registry import get_agent_class
from eval.cli import main
from eval.testing.checkpoints import find_checkpoints
from eval.testing.jobs import run_protocol
from eval.testing.metrics import metrics_table
from eval.testing.policies import policy_factory
from eval.testing.protocol import ProtocolError, ProtocolPlan, slot_order


def test_both_scenarios_and_their_metric_table():
    plan = ProtocolPlan(envs=("env_3",), scenarios=(1, 2), episodes=1, steps=40, agents=3)
    records = run_protocol(plan, policy_factory("autopilot"), ["ppo", "a3c", "ddpg"])
    s1 = records[records.scenario == 1]
    s2 = records[records.scenario == 2]
    assert sorted(s1.agent.unique()) == ["ac_0", "ac_1", "ac_2"]
    assert sorted(s1.algorithm.unique()) == ["a3c", "ddpg", "ppo"]
    assert (s1.n_vehicles > 0).all()
    # alone: no other vehicle and no pedestrian, so CV and CP do not apply
    assert (s2.n_vehicles == 0).all() and (s2.n_pedestrians == 0).all()
    table = metrics_table(records)
    assert len(table) == 6 and set(table.algorithm) == {"ppo", "a3c", "ddpg"}
    alone = table[table.scenario == 2]
    assert alone["CV"].isna().all() and alone["CP"].isna().all()
    assert table["safety"].between(0, 1).all() and table["lane_keeping"].between(0, 1).all()


def test_trained_checkpoints_are_found_and_act(tmp_path):
    obs = spaces.Box(0, 255, (84, 84, 3), np.uint8)
    for algo, act in (("ppo", spaces.Discrete(9)), ("td3", spaces.Box(-1, 1, (2,), np.float32))):
        run = tmp_path / f"env_1__{algo}__0__20260101-000000" / "checkpoints" / "ac_0"
        run.mkdir(parents=True)
        get_agent_class(algo).from_spaces(obs, act).save(run / "latest.pt")
    found = find_checkpoints(tmp_path, ["ppo", "td3"])
    assert found["ppo"].name == "latest.pt"
    make = policy_factory("trained", found)
    assert make(None, "ac_0", "td3").algo == "td3"
    with pytest.raises(ProtocolError, match="no trained checkpoint .* for dqn.*cosim train --algo dqn"):
        find_checkpoints(tmp_path, ["ppo", "dqn"])


def test_each_slot_is_driven_by_the_ac_trained_on_its_route(tmp_path):
    """The camera carries no route command: slot ac_k gets the run's own ac_k (trained on
    that spawn and goal); a slot the run never trained gets the selected AC; a
    checkpoint given with --checkpoint (``fixed``) drives every slot."""
    import json

    import torch

    from eval.testing import selection

    run = tmp_path / "env_3__dqn__0__20260101-000000"
    obs, act = spaces.Box(0, 255, (84, 84, 3), np.uint8), spaces.Discrete(9)
    for i in range(3):
        (run / "checkpoints" / f"ac_{i}").mkdir(parents=True)
        get_agent_class("dqn").from_spaces(obs, act, seed=i).save(run / "checkpoints" / f"ac_{i}" / "best.pt")
    (run / "state.json").write_text(json.dumps({"best": {"ac_0": 1.0, "ac_1": 9.0, "ac_2": 5.0}}))
    chosen = selection.choose(run).path
    assert chosen.parent.name == "ac_1"

    def same(agent, ac):
        saved = torch.load(run / "checkpoints" / ac / "best.pt", weights_only=True)["state"]["networks"]
        mine = {n: net.state_dict() for n, net in agent.networks.items()}
        return all(torch.equal(mine[n][k], saved[n][k]) for n in saved for k in saved[n])

    make = policy_factory("trained", {"dqn": chosen})
    assert same(make(None, "ac_0", "dqn"), "ac_0") and not same(make(None, "ac_0", "dqn"), "ac_1")
    assert same(make(None, "ac_2", "dqn"), "ac_2")
    assert same(make(None, "ac_5", "dqn"), "ac_1")  # no ac_5 trained: the selected AC
    given = policy_factory("trained", {"dqn": chosen}, fixed={"dqn"})
    assert same(given(None, "ac_0", "dqn"), "ac_1") and same(given(None, "ac_2", "dqn"), "ac_1")


def test_stochastic_policies_are_tested_by_sampling_them_reproducibly(tmp_path):
    """PPO/A3C/IMPALA sample their policy in the test (seeded per slot and episode); DQN,
    DDPG, TD3 and --greedy take the mode."""
    import torch

    from eval.testing.rollout import SampledPolicy

    obs_space = spaces.Box(0, 255, (84, 84, 3), np.uint8)
    paths = {}
    for algo in ("ppo", "dqn"):
        run = tmp_path / f"env_1__{algo}__0__20260101-000000" / "checkpoints" / "ac_0"
        run.mkdir(parents=True)
        get_agent_class(algo).from_spaces(obs_space, spaces.Discrete(9)).save(run / "best.pt")
        paths[algo] = run / "best.pt"
    frames = np.random.default_rng(0).integers(0, 256, (40, 84, 84, 3), dtype=np.uint8)

    def actions(policy):
        policy.reset() if hasattr(policy, "reset") else None
        return [policy.act(f, deterministic=True) for f in frames]

    make = policy_factory("trained", paths)
    ppo = make(None, "ac_0", "ppo")
    assert isinstance(ppo, SampledPolicy)
    mode = [ppo.agent.act(f, deterministic=True) for f in frames]
    own = ppo.agent.generator.get_state()
    first = actions(ppo)
    assert torch.equal(ppo.agent.generator.get_state(), own)  # the agent's own stream is untouched
    assert first != mode  # an untrained policy is near uniform: samples are not its mode
    assert actions(make(None, "ac_0", "ppo")) == first  # same slot, same first episode: same draws
    assert actions(make(None, "ac_1", "ppo")) != first  # another slot draws its own stream
    assert actions(ppo) != first  # the next episode draws anew
    assert actions(policy_factory("trained", paths, greedy=True)(None, "ac_0", "ppo")) == mode
    dqn = make(None, "ac_0", "dqn")
    assert not isinstance(dqn, SampledPolicy) and dqn.algo == "dqn"


def test_a_checkpoint_trained_on_two_frames_is_tested_on_two(tmp_path):
    """frame_stack 2 is recorded in the run's config; `cosim test`'s policies read it from
    the checkpoint (84x84x6) and stack that AC's frames, beside a one-frame AC."""
    import yaml

    from eval.testing.loading import drive, load_for_slot
    from eval.testing.rollout import StackedPolicy
    from eval.training.train import make_config, train

    cfg = make_config("ppo", "env_1", "smoke", agents=1, steps=40, frame_stack=2)
    run = train(cfg, tmp_path / "runs", quiet=True, progress=False)
    assert yaml.safe_load((run / "config.yaml").read_text())["frame_stack"] == 2
    dqn = tmp_path / "runs" / "env_1__dqn__0__20260101-000000" / "checkpoints" / "ac_0"
    dqn.mkdir(parents=True)
    get_agent_class("dqn").from_spaces(spaces.Box(0, 255, (84, 84, 3), np.uint8), spaces.Discrete(9)).save(
        dqn / "latest.pt")
    found = find_checkpoints(tmp_path / "runs", ["ppo", "dqn"])
    assert load_for_slot(found["ppo"], "ppo").observation_space.shape == (84, 84, 6)
    make = policy_factory("trained", found)
    first, second = make(None, "ac_0", "ppo"), make(None, "ac_1", "ppo")
    assert isinstance(first, StackedPolicy) and first.frame_stack == 2
    assert first.history is not second.history  # each AC keeps its own frames
    assert not isinstance(make(None, "ac_1", "dqn"), StackedPolicy)
    assert drive(load_for_slot(found["dqn"], "dqn")).algo == "dqn"
    plan = ProtocolPlan(envs=("env_1",), scenarios=(1,), episodes=1, steps=5, agents=2)
    records = run_protocol(plan, make, ["ppo", "dqn"])  # a 3-channel frame would not fit PPO's CNN
    assert sorted(records.algorithm.unique()) == ["dqn", "ppo"] and len(records) == 5 * 2
    bad = tmp_path / "bad.pt"
    get_agent_class("ppo").from_spaces(spaces.Box(0, 255, (84, 84, 4), np.uint8), spaces.Discrete(9)).save(bad)
    with pytest.raises(ProtocolError, match=r"shape \(84, 84, 4\).*K of them stacked"):
        load_for_slot(bad, "ppo")


def test_a_checkpoint_trained_with_an_action_repeat_is_tested_holding_its_actions(tmp_path):
    """--set action_repeat=2: the budget counts environment steps (20 decisions for 40), the
    checkpoint carries the repeat, and the test holds each of its actions for 2 steps."""
    import yaml

    from eval.testing.loading import action_repeat_of, drive, load_for_slot
    from eval.testing.rollout import RepeatPolicy, StackedPolicy
    from eval.training.runfolder import read_state
    from eval.training.train import make_config, train

    cfg = make_config("ppo", "env_1", "smoke", agents=1, steps=40, hyper={"action_repeat": "2"})
    run = train(cfg, tmp_path / "runs", quiet=True, progress=False)
    assert yaml.safe_load((run / "config.yaml").read_text())["agent_config"]["action_repeat"] == 2
    assert read_state(run)["env_steps"] == 40
    agent = load_for_slot(find_checkpoints(tmp_path / "runs", ["ppo"])["ppo"], "ppo")
    assert action_repeat_of(agent) == 2
    policy = drive(agent)
    assert isinstance(policy, RepeatPolicy) and policy.k == 2 and isinstance(policy.policy, StackedPolicy)
    decided = []
    act = policy.policy.act
    policy.policy.act = lambda obs, deterministic=True: decided.append(1) or act(obs)
    records = run_protocol(ProtocolPlan(envs=("env_1",), scenarios=(2,), episodes=1, steps=7, agents=1),
                           lambda env, slot, algo: policy, ["ppo"])
    assert len(records) == 7 and len(decided) == 4  # steps 0, 2, 4, 6


def test_scenario_1_rotates_the_algorithms_over_the_spawn_slots():
    algos = ["ppo", "a3c", "ddpg"]
    assert slot_order(algos, 0) == algos
    assert slot_order(algos, 1) == ["ddpg", "ppo", "a3c"]  # algorithm i drives ac_{(i + 1) mod 3}
    assert slot_order(algos, 4) == slot_order(algos, 1)
    assert slot_order(algos, 1, rotate=False) == algos
    # over N episodes every algorithm starts once from every slot
    assert all(sorted(slot_order(algos, e)[k] for e in range(3)) == sorted(algos) for k in range(3))

    plan = ProtocolPlan(envs=("env_1",), scenarios=(1,), episodes=3, steps=4, agents=3)
    records = run_protocol(plan, policy_factory("autopilot"), algos)
    for e in range(3):
        ep = records[records.episode == e]
        assert ep.seed.unique().tolist() == [plan.seed + e]
        assert dict(ep.groupby("agent").algorithm.first()) == dict(
            zip(["ac_0", "ac_1", "ac_2"], slot_order(algos, e), strict=True))
        # the spawn of a slot stays put; the algorithm at it changes
        first = ep[ep.step == 1].set_index("agent")
        assert first.loc["ac_0", "algorithm"] == slot_order(algos, e)[0]
    starts = records[records.step == 1].groupby("agent").spawn_x.nunique()
    assert (starts == 1).all()
    fixed = run_protocol(ProtocolPlan(envs=("env_1",), scenarios=(1,), episodes=2, steps=2,
                                      agents=3, rotate=False), policy_factory("autopilot"), algos)
    assert (fixed[fixed.agent == "ac_0"].algorithm == "ppo").all()
    # the report and the science plan say which placement and actions a test used
    from eval.testing.protocol import rules

    assert rules(plan)["scenario_1_slots"].startswith("rotated")
    assert rules(ProtocolPlan(rotate=False, greedy=True)) == {**rules(plan), **{
        "scenario_1_slots": "fixed: algorithm i drives ac_i", "actions": "every policy's mode (--greedy)"}}


def test_cli_test_without_runs_says_how_to_get_them(tmp_path, capsys):
    assert main(["test", "--runs", str(tmp_path / "none"), "--quiet"]) == 2
    assert "--policy autopilot" in capsys.readouterr().err


def test_corrupt_checkpoint_is_a_one_line_error(tmp_path, capsys):
    ckpt = tmp_path / "env_1__ppo__0__20260101-000000" / "checkpoints" / "ac_0" / "best.pt"
    ckpt.parent.mkdir(parents=True)
    ckpt.write_bytes(b"not a checkpoint")
    assert main(["test", "--agents", "1", "--runs", str(tmp_path), "--envs", "env_1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "best.pt" in err and "corrupt" in err and err.count("\n") == 1


def test_resume_of_a_folder_that_is_not_a_run(tmp_path, capsys):
    assert main(["train", "--resume", str(tmp_path)]) == 2
    assert "not a training run folder" in capsys.readouterr().err


def test_cli_test_adds_the_reference_rows_to_the_report(tmp_path, capsys):
    code = main(["test", "--policy", "autopilot", "--agents", "2", "--envs", "env_4",
                 "--scenario", "1", "--episodes", "1", "--steps", "30", "--quiet",
                 "--references", "autopilot,always-forward", "--out", str(tmp_path)])
    assert code == 0
    (report,) = tmp_path.glob("*/report.md")
    text = report.read_text()
    assert "Reference rows" in text and "| always-forward |" in text and "| autopilot |" in text
    refs = pd.read_csv(report.parent / "references.csv")
    assert set(refs.policy) == {"autopilot", "always-forward"} and set(refs.env) == {"env_4"}
    # a name outside the suite is refused with the valid ones
    assert main(["test", "--policy", "autopilot", "--references", "backwards", "--quiet",
                 "--out", str(tmp_path)]) == 2
    assert "always-forward" in capsys.readouterr().err


def test_algos_picks_the_algorithms_tested_in_paper_order(tmp_path):
    code = main(["test", "--policy", "autopilot", "--algos", "td3", "ppo", "--envs", "env_1",
                 "--scenario", "1", "--episodes", "1", "--steps", "5", "--no-replays",
                 "--references", "none", "--out", str(tmp_path), "--quiet"])
    assert code == 0
    (long,) = tmp_path.glob("*/rq1_long.csv")
    assert list(dict.fromkeys(pd.read_csv(long)["algorithm"])) == ["ppo", "td3"]
    prov = json.loads((long.parent / "provenance.json").read_text())
    assert prov["command"].split()[:5] == ["cosim", "test", "--algos", "td3", "ppo"]


def test_worker_processes_give_the_same_records_in_the_same_order(tmp_path):
    """`run_protocol(workers=2)` hands trained checkpoints to two processes (they load them
    again there) and returns what one process does, in its order, telling the same progress."""
    import torch

    obs = spaces.Box(0, 255, (84, 84, 3), np.uint8)
    found = {}
    for algo, act in (("ppo", spaces.Discrete(9)), ("dqn", spaces.Discrete(9)),
                      ("td3", spaces.Box(-1, 1, (2,), np.float32))):
        run = tmp_path / f"env_1__{algo}__0__20260101-000000" / "checkpoints" / "ac_0"
        run.mkdir(parents=True)
        get_agent_class(algo).from_spaces(obs, act, seed=3).save(run / "best.pt")
        found[algo] = run / "best.pt"
    plan = ProtocolPlan(envs=("env_1",), scenarios=(1, 2), episodes=2, steps=12, agents=3)
    told = {1: [], 2: []}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as in each worker: the networks' sums in one order
    try:
        one = run_protocol(plan, policy_factory("trained", found), list(found), progress=told[1].append)
    finally:
        torch.set_num_threads(threads)
    two = run_protocol(plan, policy_factory("trained", found), list(found), progress=told[2].append,
                       workers=2)
    assert len(one) == 2 * 12 * 3 + 3 * 2 * 12  # Scenario 1: 2 episodes x 3 ACs; 2: 3 ACs alone
    pd.testing.assert_frame_equal(one, two)
    assert sorted(told[1]) == sorted(told[2]) == ["env_1 scenario 1", "env_1 scenario 2 dqn",
                                                  "env_1 scenario 2 ppo", "env_1 scenario 2 td3"]
    with pytest.raises(ProtocolError, match="cannot go to another process.*workers=1"):
        run_protocol(plan, lambda env, agent, algo: None, list(found), workers=2)


def test_cli_test_runs_its_episodes_in_worker_processes(tmp_path, capsys):
    code = main(["test", "--policy", "autopilot", "--algos", "td3", "ppo", "--envs", "env_1",
                 "--scenario", "both", "--episodes", "1", "--steps", "5", "--no-replays",
                 "--references", "none", "--workers", "2", "--out", str(tmp_path), "--quiet"])
    assert code == 0
    (records,) = tmp_path.glob("*/records.parquet")
    rec = pd.read_parquet(records)
    assert sorted(rec.groupby("scenario").size().items()) == [(1, 10), (2, 10)]
    with pytest.raises(SystemExit):
        main(["test", "--policy", "autopilot", "--workers", "0", "--out", str(tmp_path)])
    assert "--workers: must be >= 1, got 0" in capsys.readouterr().err
