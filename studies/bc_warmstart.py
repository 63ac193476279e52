"""Can the networks drive from what an AC observes? Behaviour cloning of the discrete autopilot,
then PPO from it (issue 25, a diagnostic beside the pure-RL pilots).

    python studies/bc_warmstart.py --out bc                     # demos, clone, test the clone
    python studies/bc_warmstart.py --out bc                     # again after a kill: continues
    python studies/bc_warmstart.py --smoke --out /tmp/bc        # ~1 minute, the CI check

1. **Demonstrations** (``OUT/demos/<env>.npz``, one file per environment, kept): the discrete
   autopilot (eval.testing.rollout.AutopilotPolicy: the scripted driver restricted to
   Discrete(9), privileged) drives the run's ACs in the training env of ``cosim train --obs
   nav --share-params --set action_repeat=2 --preset standard`` (eval.training.trainer.make_env:
   4 stacked frames, the nav measurements, each action held 2 steps), on training seeds 0, 1,
   ... (never the test's held-out 10,000+). With probability ``--noise`` an AC executes a
   uniformly random action instead, while the label stays the autopilot's: the states a
   learner's mistakes lead to, with the way back (Laskey et al. 2017, DART). Kept per decision:
   the observation, the autopilot's action and the discounted return (gamma of PPO's config,
   over the decisions' summed rewards, times the preset's reward_scale).
2. **Clone** (``OUT/clones/clone_0.pt``): one PPO network of that run config for every
   environment's demonstrations (agents/imitation.py ``clone``: cross-entropy on the actions,
   squared error on the returns).
2b. **DAgger** (Ross et al. 2011), ``--dagger N`` rounds: round i lets clone i-1 drive (its
   sampled actions, no added noise) while the autopilot labels every decision
   (``OUT/demos/<env>_dagger<i>.npz``), then trains that clone further on all the
   demonstrations so far for ``--dagger-epochs`` (``OUT/clones/clone_<i>.pt``). The states a
   clone's own mistakes lead to (a queue it is about to run into) get the autopilot's answer.
   The last clone is ``OUT/bc_ppo.pt``, a full PPO checkpoint.
3. **Test the clone** as the pilots test a run (studies/pilot_task.py): its ACs together, every
   slot driven by the clone, the test's rules, held-out seeds 10,000+, PPO sampled; written to
   ``OUT/test/<env>.parquet`` and ``OUT/summary.md`` beside the pilots' reference rows.

RL from the clone is a pilot arm: ``python studies/pilot_task.py --arms warm --init-from
OUT/bc_ppo.pt ...`` (``cosim train --init-from``, docs/agents.md "Warm start").
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
for path in (ROOT, ROOT / "studies"):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pilot_task  # noqa: E402
from science import _write  # noqa: E402

from cosim.errors import CosimError  # noqa: E402
from eval.testing.validity import HELD_OUT_SEED  # noqa: E402

FLAGS = {"obs": "nav", "share_params": True, "hyper": {"action_repeat": "2"}}
"""The run config the clone is built for: the pilots' nav-shared-r2 arm."""
SMOKE = {"preset": "smoke", "envs": ["env_4"], "episodes": 1, "epochs": 1, "test_episodes": 1,
         "test_steps": 40}


def say(msg: str) -> None:
    print(f"[bc] {msg}", file=sys.stderr, flush=True)


def parse(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("bc_warmstart"), help="study folder")
    p.add_argument("--envs", nargs="+", default=None, help="default: env_3 env_4")
    p.add_argument("--preset", default=None, help="run preset of the env and agent config (default: standard)")
    p.add_argument("--episodes", type=int, default=None, help="demonstration episodes per environment (default 12)")
    p.add_argument("--noise", type=float, default=0.2, help="chance an AC executes a random action (default 0.2)")
    p.add_argument("--epochs", type=int, default=None, help="cloning epochs (default 6)")
    p.add_argument("--dagger", type=int, default=0,
                   help="DAgger rounds after the first clone (default 0); all rounds' demonstrations are held in "
                        "memory, ~3 GB per round of 12 episodes in 2 environments")
    p.add_argument("--dagger-epochs", type=int, default=3, help="epochs of each DAgger round (default 3)")
    p.add_argument("--test-episodes", type=int, default=None, help="held-out test episodes (default 5)")
    p.add_argument("--test-steps", type=int, default=None, help="steps per test episode (default: the horizon)")
    p.add_argument("--smoke", action="store_true", help="the CI check: " + " ".join(
        f"--{k.replace('_', '-')} {' '.join(map(str, v)) if isinstance(v, list) else v}" for k, v in SMOKE.items()))
    args = pilot_task.smoke_defaults(p.parse_args(argv), SMOKE)
    args.envs = args.envs or ["env_3", "env_4"]
    args.preset = args.preset or "standard"
    args.episodes = args.episodes or 12
    args.epochs = args.epochs or 6
    args.test_episodes = args.test_episodes or 5
    if min(args.episodes, args.epochs, args.test_episodes, args.dagger_epochs) < 1 or args.dagger < 0 or not (
            0 <= args.noise < 1):
        p.error("--episodes, --epochs, --dagger-epochs and --test-episodes must be >= 1, --dagger >= 0, "
                "--noise in [0, 1)")
    args.out = args.out.resolve()
    return args


def run_config(env: str, preset: str):
    from eval.training.config import make_config

    return make_config("ppo", env, preset, **FLAGS)


# -- 1. demonstrations -------------------------------------------------------------------------
def discounted(rewards: list[float], gamma: float) -> np.ndarray:
    """Discounted returns from each step of one trajectory (the last step's: its reward)."""
    out, acc = np.zeros(len(rewards), np.float32), 0.0
    for t in range(len(rewards) - 1, -1, -1):
        acc = rewards[t] + gamma * acc
        out[t] = acc
    return out


def collect(env_name: str, args, driver=None, first_seed: int = 0) -> dict[str, np.ndarray]:
    """Demonstrations of one environment (module docstring, step 1): the autopilot's labels;
    it drives (with ``--noise``), or ``driver`` (a PPO agent, sampled) does (step 2b)."""
    from eval.testing.rollout import AutopilotPolicy
    from eval.training.trainer import make_env

    cfg = run_config(env_name, args.preset)
    gamma, scale = cfg.agent_config.gamma, cfg.agent_config.reward_scale
    env = make_env(cfg)
    base = env.unwrapped
    rng = np.random.default_rng(0)
    images, measures, actions, returns, goals = [], [], [], [], []
    try:
        for episode in range(args.episodes):
            obs, _ = env.reset(seed=first_seed + episode)
            pilots = {ac: AutopilotPolicy(base, ac) for ac in env.agents}
            trail = {ac: [] for ac in env.agents}  # (image, measurements, action, reward)
            while env.agents:
                labels = {ac: int(pilots[ac].act(None)) for ac in env.agents}
                if driver is not None:
                    executed = dict(zip(labels, sampled(driver, [obs[ac] for ac in labels], rng), strict=True))
                else:
                    executed = {ac: (int(rng.integers(9)) if rng.random() < args.noise else a)
                                for ac, a in labels.items()}
                now = obs
                obs, rewards, terms, truncs, infos = env.step(executed)
                for ac, a in labels.items():
                    trail[ac].append((now[ac]["image"], now[ac]["measurements"], a, float(rewards[ac])))
                    if terms.get(ac) or truncs.get(ac):
                        goals.append(bool(infos.get(ac, {}).get("goal_reached", False)))
            for steps in trail.values():
                images += [s[0] for s in steps]
                measures += [s[1] for s in steps]
                actions += [s[2] for s in steps]
                returns.append(discounted([s[3] for s in steps], gamma) * scale)
    finally:
        env.close()
    return {"image": np.stack(images), "measurements": np.stack(measures).astype(np.float32),
            "actions": np.asarray(actions, np.int64), "returns": np.concatenate(returns),
            "goals": np.asarray(goals, bool)}


def sampled(agent, obs: list, rng: np.random.Generator) -> list[int]:
    """Actions drawn from a PPO agent's policy for a list of observations, in one forward pass."""
    import torch

    from agents import observations
    from agents.networks import obs_to_tensor

    with torch.no_grad():
        logits, _ = agent.net(obs_to_tensor(observations.stack(obs), agent.device))
    probs = torch.softmax(logits, -1).cpu().numpy().astype(np.float64)
    return [int(rng.choice(len(p), p=p / p.sum())) for p in probs]


def demos(out: Path, env_name: str, args, round_: int = 0, driver=None) -> dict[str, np.ndarray]:
    """``OUT/demos/<env>.npz`` (round 0, the autopilot drives) or ``<env>_dagger<i>.npz``
    (round i, ``driver`` drives), collected once; each round on its own training seeds."""
    path = out / "demos" / (f"{env_name}.npz" if round_ == 0 else f"{env_name}_dagger{round_}.npz")
    if not path.exists():
        start = time.monotonic()
        data = collect(env_name, args, driver, first_seed=1000 * round_)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, **data)
        tmp.replace(path)
        who = f"autopilot with noise {args.noise}" if driver is None else f"clone {round_ - 1}"
        say(f"demos {env_name} round {round_}: {len(data['actions'])} decisions, goal rate "
            f"{data['goals'].mean():.2f} driven by the {who} ({time.monotonic() - start:.0f} s)")
    with np.load(path) as f:
        return {k: f[k] for k in f.files}


# -- 2. clone ----------------------------------------------------------------------------------
def build_clone(out: Path, args) -> Path:
    """``OUT/bc_ppo.pt``: a PPO agent of the run config cloned on every environment's demos,
    then ``--dagger`` rounds (module docstring, steps 2 and 2b); each clone kept, so a rerun
    goes on from the last one written."""
    import shutil

    import agents as agents_pkg
    from agents.registry import get_agent_class
    from eval.training.trainer import make_env

    final = out / "bc_ppo.pt"
    if final.exists():
        return final
    data = [demos(out, env, args) for env in args.envs]
    cfg = run_config(args.envs[0], args.preset)
    probe = make_env(cfg)
    try:
        agent = get_agent_class("ppo").from_spaces(probe.observation_space("ac_0"), probe.action_space("ac_0"),
                                                   cfg.agent_config, seed=0)
    finally:
        probe.close()
    for round_ in range(args.dagger + 1):
        if round_ > 0:
            data += [demos(out, env, args, round_, agent) for env in args.envs]
        path = out / "clones" / f"clone_{round_}.pt"
        if path.exists():
            agent = agents_pkg.load(path)
            continue
        fit(agent, data, args.epochs if round_ == 0 else args.dagger_epochs, f"clone {round_}")
        path.parent.mkdir(parents=True, exist_ok=True)
        agent.save(path)
    shutil.copyfile(path, final)
    return final


def fit(agent, data: list[dict], epochs: int, name: str) -> None:
    """Clone ``agent`` on the demonstrations ``data`` (every round so far) for ``epochs``."""
    from agents.imitation import clone

    obs = [{k: d[k] for k in ("image", "measurements")} for d in data]  # not copied into one array
    actions = np.concatenate([d["actions"] for d in data])
    start = time.monotonic()

    def report(epoch: int, m: dict) -> None:
        say(f"{name} epoch {epoch + 1}/{epochs} on {len(actions)} decisions: accuracy {m['accuracy']:.3f}, "
            f"cross-entropy {m['cross_entropy']:.3f}, value loss {m['value_loss']:.4f} "
            f"({time.monotonic() - start:.0f} s)")

    clone(agent, obs, actions, np.concatenate([d["returns"] for d in data]), epochs=epochs, on_epoch=report)


# -- 3. test -----------------------------------------------------------------------------------
def test_clone(out: Path, path: Path, env_name: str, args) -> pd.DataFrame:
    """``OUT/test/<env>.parquet``: every slot driven by the clone (module docstring, step 3)."""
    from eval.testing.protocol import ProtocolPlan
    from eval.testing.session import TestRequest, run_test

    done = out / "test" / f"{env_name}.parquet"
    if done.exists():
        return pd.read_parquet(done)
    cfg = run_config(env_name, args.preset)
    steps = pilot_task.test_steps(args, env_name)
    plan = ProtocolPlan(envs=(env_name,), scenarios=(1,), episodes=args.test_episodes, steps=steps,
                        seed=HELD_OUT_SEED, agents=cfg.agents, rotate=False)
    records = run_test(TestRequest(plan, ("ppo",) * cfg.agents, checkpoints={env_name: {"ppo": path}},
                                   fixed=("ppo",))).records
    _write(records, done)
    return records


def summary(out: Path, args) -> str:
    """The clone's rows beside the pilots' references, per environment (pilot_task's tables)."""
    parts = []
    for env_name in args.envs:
        records = pd.read_parquet(out / "test" / f"{env_name}.parquet")
        routes = pilot_task.slot_routes(env_name)
        refs = pilot_task.references(out, env_name, "new", pilot_task.REFERENCES, records["agent"].nunique(),
                                     args.test_episodes, pilot_task.test_steps(args, env_name))
        rows = [pilot_task.slot_table(pilot_task.per_slot(records), routes, env=env_name, arm="bc",
                                      algo="ppo", car="new", row="bc clone ppo")]
        refs = refs.rename(columns={"agent": "slot", "collision_steps": "contact_steps"})
        rows += [pilot_task.slot_table(g, routes, env=env_name, arm="reference", algo=policy, car="new",
                                       row=f"ref: {policy}") for policy, g in refs.groupby("policy", sort=False)]
        md, _ = pilot_task.env_summary(pd.concat(rows, ignore_index=True), env_name)
        parts.append(f"## {env_name}\n\n{md}\n")
    return "\n".join(parts)


def main(argv=None) -> int:
    args = parse(argv)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    try:
        path = build_clone(out, args)
        pilot_task._acting_threads()  # the tests only act (cloning used every core)
        for env_name in args.envs:
            start = time.monotonic()
            s = pilot_task.per_slot(test_clone(out, path, env_name, args))
            say(f"test {env_name}: return {s['return'].mean():.1f}, goal rate {s['goal'].mean():.2f}, "
                f"contact steps {s['contact_steps'].mean():.1f} per AC-episode ({time.monotonic() - start:.0f} s)")
    except (CosimError, OSError) as exc:
        print(f"bc_warmstart: error: {exc}", file=sys.stderr)
        return 2
    text = summary(out, args)
    (out / "summary.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
