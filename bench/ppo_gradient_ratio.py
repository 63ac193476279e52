"""How much of PPO's shared-encoder gradient is the value loss's? (issue 59 item 2)

PPO on images shares one Nature CNN between the policy and the value head (agents/networks.py
ActorCritic), so both losses train it. This trains ``--agents`` PPO ACs on the real camera
env (default env_2, Three-way, the ``standard`` preset: 4 frames, reward scale 0.01, rollouts
of 512, minibatches of 64, 4 epochs) as `cosim train` does (eval.training.train.make_config
and make_env, one env in process, agents seeded seed + k) and, at every minibatch of the
first ``--updates`` updates of every AC, before the optimiser step, takes apart the gradient
on the CNN trunk (the encoder: convolutions and the 512-unit layer):

* value: the gradient of ``vf_coef * v_loss``;
* policy: the gradient of the rest of the loss, ``pg_loss + kl_coef * kl - ent_coef * entropy``;
* ratio: ||value|| / ||policy|| on the trunk;
* clip scale: ``min(1, max_grad_norm / ||whole gradient||)``, the factor clip_grad_norm_
  multiplies every gradient (the policy's too) by.

Each arm (``--arms``, each a set of ``--set``-style changes, ``-`` for none) trains from the
same seed on the same scenario seeds; the first rollout's frames are the same in every arm
(the same initial weights act), the second's are not. The table gives, per arm and update, the
median over the ACs' minibatches, the first minibatch's, and the ACs' value loss.

    python bench/ppo_gradient_ratio.py [--env env_2] [--agents 6] [--updates 2]
        [--arms value_norm=none value_norm=shared] [--seed 0] [--json out.json]
"""

from __future__ import annotations

import argparse
import functools
import json
import statistics
import time

import torch

from agents.loop import run_loop
from agents.ppo import PPO
from agents.vector import make_vector_env
from eval.training.train import make_config, make_env


class MeasuredPPO(PPO):
    """PPO that records, at each minibatch of its first ``measure_updates`` updates, the value
    and policy parts of the gradient on its encoder (then takes the usual step)."""

    measure_updates = 2

    def _build(self) -> None:
        super()._build()
        self.records: list[dict] = []

    def _minibatch_step(self, obs, actions, old_log_probs, old_logits, advantages, returns):
        if self.iterations < self.measure_updates:
            self.records.append(self._measure(obs, actions, old_log_probs, old_logits, advantages, returns))
        return super()._minibatch_step(obs, actions, old_log_probs, old_logits, advantages, returns)

    def _measure(self, *batch) -> dict:
        cfg = self.config
        terms = self.losses(*batch)
        trunk = [p for p in self.net.encoder.parameters()]
        value = cfg.vf_coef * terms["v_loss"]
        policy = terms["pg_loss"] + self.kl_coef * terms["kl"] - cfg.ent_coef * terms["entropy"]
        g_value = torch.autograd.grad(value, trunk, retain_graph=True, allow_unused=True)
        g_policy = torch.autograd.grad(policy, trunk, retain_graph=True, allow_unused=True)
        g_all = torch.autograd.grad(terms["loss"], list(self.net.parameters()), allow_unused=True)
        value_norm, policy_norm, total = (_norm(g) for g in (g_value, g_policy, g_all))
        return {"update": self.iterations, "value": value_norm, "policy": policy_norm,
                "ratio": value_norm / max(policy_norm, 1e-30), "clip_scale": min(1.0, cfg.max_grad_norm / max(total, 1e-30)),
                "v_loss": terms["v_loss"].item(), "pg_loss": terms["pg_loss"].item()}


def _norm(grads) -> float:
    return float(torch.sqrt(sum((g.double() ** 2).sum() for g in grads if g is not None)))


def _changes(arm: str) -> dict[str, str]:
    return {} if arm == "-" else dict(item.split("=", 1) for item in arm.split(","))


def run_arm(arm: str, env: str, agents: int, updates: int, seed: int) -> dict:
    """Train ``agents`` MeasuredPPO ACs until each has made ``updates`` updates; their records."""
    cfg = make_config("ppo", env, "standard", agents=agents, seed=seed, envs=1, validation_episodes=0,
                      hyper=_changes(arm))
    venv = make_vector_env([functools.partial(make_env, cfg, seed)])
    MeasuredPPO.measure_updates = updates
    try:
        learners = {f"ac_{k}": MeasuredPPO.from_spaces(venv.observation_space(f"ac_{k}"), venv.action_space(f"ac_{k}"),
                                                       cfg.agent_config, seed=seed + k) for k in range(agents)}

        def done(progress) -> bool:
            return all(a.iterations >= updates for a in learners.values())

        t0 = time.monotonic()
        stats = run_loop(learners, venv, 10**9, callback=done, seed=seed, learner_threads=2)
    finally:
        venv.close()
    return {"arm": arm, "env_steps": stats.env_steps, "seconds": time.monotonic() - t0,
            "value_stats": {a: learner.value_stats.state() for a, learner in learners.items()},
            "records": {a: learner.records for a, learner in learners.items()}}


def summarise(result: dict, updates: int) -> list[dict]:
    rows = []
    for u in range(updates):
        recs = [r for records in result["records"].values() for r in records if r["update"] == u]
        firsts = [next(r for r in records if r["update"] == u) for records in result["records"].values()
                  if any(r["update"] == u for r in records)]
        if not recs:
            continue
        rows.append({
            "arm": result["arm"], "update": u + 1, "minibatches": len(recs),
            "ratio_median": statistics.median(r["ratio"] for r in recs),
            "ratio_first": statistics.median(r["ratio"] for r in firsts),
            "ratio_range": (min(r["ratio"] for r in recs), max(r["ratio"] for r in recs)),
            "clip_median": statistics.median(r["clip_scale"] for r in recs),
            "clip_range": (min(r["clip_scale"] for r in recs), max(r["clip_scale"] for r in recs)),
            "v_loss_first": statistics.median(r["v_loss"] for r in firsts),
        })
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="env_2")
    parser.add_argument("--agents", type=int, default=6)
    parser.add_argument("--updates", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--arms", nargs="+", default=["value_norm=none", "value_norm=shared"],
                        help="each a comma-separated list of PPO --set changes ('-': the preset as it is)")
    parser.add_argument("--json", default=None, help="write every record here")
    args = parser.parse_args()
    torch.set_num_threads(1)
    results = []
    for arm in args.arms:
        results.append(run_arm(arm, args.env, args.agents, args.updates, args.seed))
        print(f"{arm}: {results[-1]['env_steps']} env steps, {results[-1]['seconds']:.0f} s", flush=True)
    print(f"\nPPO, {args.env}, {args.agents} ACs, standard preset, seed {args.seed}: gradient on the shared "
          f"CNN trunk, value part / policy part; clip scale = min(1, max_grad_norm / ||gradient||)\n")
    print("| arm | update | minibatches | ratio, first minibatch (median of ACs) | ratio, median [range] "
          "| clip scale, median [range] | value loss, first minibatch |")
    print("|---|---|---|---|---|---|---|")
    for result in results:
        for r in summarise(result, args.updates):
            print(f"| {r['arm']} | {r['update']} | {r['minibatches']} | {r['ratio_first']:.1f} | {r['ratio_median']:.1f} "
                  f"[{r['ratio_range'][0]:.1f}, {r['ratio_range'][1]:.1f}] | {r['clip_median']:.3f} "
                  f"[{r['clip_range'][0]:.3f}, {r['clip_range'][1]:.3f}] | {r['v_loss_first']:.3g} |")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1, default=float)


if __name__ == "__main__":
    main()
