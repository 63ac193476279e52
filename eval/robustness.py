"""Cross-play and robustness sweeps of ``cosim test`` (issue 13).

Cross-play (``--cross-play``): in each environment, the AC of one algorithm (the
*ego*, ``ac_0``) drives among ``group - 1`` ACs that all run one *partner* policy:
each other algorithm's AC, its own algorithm's (self-play) or the autopilot.
The matrix (rows: ego, columns: partner) gives the ego's collision rate (share of
episodes with a collision step with a vehicle) and goal rate (share reaching its
goal), pooled over environments, with 95% bootstrap intervals: who is dangerous
to whom. Files: ``crossplay.csv`` (per environment and pooled), ``crossplay.md``,
``crossplay_heatmap.pdf/.png``.

Robustness sweeps (``--sweep KIND=L1,L2,...``), Scenario 1 conditions, each level
a full set of episodes:

- ``density``: the background traffic's flow rates times the level (SUMO --scale);
- ``camera_noise``: Gaussian pixel noise of standard deviation level x 255;
- ``action_noise``: continuous actions + Gaussian noise of std level (clipped);
  discrete actions replaced by a random one with probability level;
- ``dropout``: each camera frame is lost with probability level (the policy sees
  the last frame it received).

The perturbations are seeded (plan seed, AC index): the same command gives the same
records. Files: ``sweep_<kind>.csv`` (per level, algorithm and metric: mean, CI, n)
and ``sweep_<kind>.pdf/.png`` (metrics against the level, one line per algorithm
with its interval band).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import pandas as pd

from eval.protocol import CONTINUOUS, ProtocolError
from eval.report import SCENARIO_NAMES, algo_order, bootstrap_ci, per_episode  # noqa: F401
from eval.rollout import AutopilotPolicy, run_episodes

SWEEP_KINDS = ("density", "camera_noise", "action_noise", "dropout")
SWEEP_METRICS = (("safety", "Safety (collision-\nfree episodes)"), ("lane_keeping", "Lane keeping\n(1 - OS)"),
                 ("DISTANCE", "DISTANCE (m)"), ("SPEED", "SPEED (km/h)"))


def parse_sweeps(items: Sequence[str]) -> dict[str, list[float]]:
    """``["density=0.5,1,2"]`` -> ``{"density": [0.5, 1.0, 2.0]}``; ProtocolError when malformed."""
    out: dict[str, list[float]] = {}
    for item in items:
        kind, sep, levels = item.partition("=")
        if kind not in SWEEP_KINDS or not sep:
            raise ProtocolError(f"--sweep {item!r}: write KIND=L1,L2,... with KIND one of "
                                f"{', '.join(SWEEP_KINDS)}, e.g. --sweep density=0.5,1,2")
        try:
            values = [float(v) for v in levels.split(",") if v.strip()]
        except ValueError:
            raise ProtocolError(f"--sweep {item!r}: the levels must be numbers") from None
        bad = [v for v in values if v < 0 or (kind in ("dropout", "action_noise") and v > 1)
               or not np.isfinite(v)]
        if not values or bad:
            raise ProtocolError(f"--sweep {item!r}: give levels >= 0 (dropout and action_noise "
                                "at most 1)")
        out[kind] = values
    return out


class Perturbed:
    """A policy seen through a perturbation: noisy or lost camera frames, noisy actions."""

    def __init__(self, policy, space, kind: str, level: float, seed: int):
        self.policy, self.space, self.kind, self.level = policy, space, kind, float(level)
        self.seed = seed
        self.rng = np.random.default_rng(seed)
        self.last = None

    def reset(self) -> None:
        if hasattr(self.policy, "reset"):
            self.policy.reset()
        self.last = None

    def act(self, obs, deterministic: bool = True):
        from eval.rollout import _act

        if self.kind == "camera_noise" and self.level > 0:
            noise = self.rng.normal(0.0, self.level * 255.0, obs.shape)
            obs = np.clip(obs.astype(np.float32) + noise, 0, 255).astype(np.uint8)
        elif self.kind == "dropout":
            lost = self.last is not None and self.rng.random() < self.level
            obs = self.last if lost else obs
            self.last = obs
        action = _act(self.policy, obs)
        if self.kind == "action_noise" and self.level > 0:
            if hasattr(self.space, "n"):
                if self.rng.random() < self.level:
                    action = int(self.rng.integers(0, self.space.n))
            else:
                action = np.clip(np.asarray(action, np.float32)
                                 + self.rng.normal(0.0, self.level, 2).astype(np.float32), -1, 1)
        return action


def _env(scenario, types: list[str], steps: int):
    from cosim.env import CosimParallelEnv

    return CosimParallelEnv(scenario, num_agents=len(types), action_types=types,
                            terminate_on_collision=False, horizon=steps)


def _kind(name: str) -> str:
    return "continuous" if name in CONTINUOUS else "discrete"


def run_cross_play(plan, make_policy: Callable, algos: Sequence[str], group: int = 3,
                   progress: Callable[[str], None] | None = None) -> pd.DataFrame:
    """Records of every (ego, partner) pair in every environment of the plan."""
    partners = [*algos, "autopilot"]
    seeds = [plan.seed + e for e in range(plan.episodes)]
    frames = []
    for env_name in plan.envs:
        for ego in algos:
            for partner in partners:
                types = [_kind(ego)] + [_kind(partner) if partner != "autopilot" else "continuous"] * (group - 1)
                env = _env(env_name, types, plan.steps)
                try:
                    names = {a: (ego if i == 0 else partner) for i, a in enumerate(env.possible_agents)}
                    policies = {a: make_policy(env, a, ego) if i == 0 else
                                (AutopilotPolicy(env, a) if partner == "autopilot"
                                 else make_policy(env, a, partner))
                                for i, a in enumerate(env.possible_agents)}
                    rec = run_episodes(env, policies, seeds, algorithms=names)
                finally:
                    env.close()
                frames.append(rec.assign(env=env_name, scenario=1, ego=ego, partner=partner))
                if progress:
                    progress(f"{env_name} cross-play {ego} among {partner}")
    return pd.concat(frames, ignore_index=True)


def cross_play_table(records: pd.DataFrame, dt: float | None = None) -> pd.DataFrame:
    """Per (env or 'all', ego, partner): the ego's collision and goal rates with 95% CIs."""
    ego = records[records["agent"] == "ac_0"]
    rows = []
    for (ego_algo, partner), g in ego.groupby(["ego", "partner"], sort=False):
        per = per_episode(g.drop(columns=["ego", "partner"]), dt)
        per["crash"] = (per["CV"].fillna(0) > 0).astype(float)
        per["goal"] = per["goal"].astype(float)
        for env, sub in [*per.groupby("env", sort=True), ("all", per)]:
            row = {"env": env, "ego": ego_algo, "partner": partner}
            for m, name in (("crash", "collision_rate"), ("goal", "goal_rate")):
                mean, lo, hi, n = bootstrap_ci(sub[m].to_numpy())
                row.update({name: mean, f"{name}_low": lo, f"{name}_high": hi})
            row["n"] = n
            rows.append(row)
    return pd.DataFrame(rows)


def cross_play_markdown(table: pd.DataFrame, labels: dict) -> str:
    allt = table[table["env"] == "all"]
    egos = algo_order(allt["ego"].unique())
    partners = [p for p in [*egos, "autopilot"] if p in set(allt["partner"])]
    t = allt.set_index(["ego", "partner"])
    lines = ["| ego \\ among | " + " | ".join(labels.get(p, p) for p in partners) + " |",
             "|---|" + "---|" * len(partners)]
    for e in egos:
        cells = []
        for p in partners:
            r = t.loc[(e, p)]
            cells.append(f"{r.collision_rate:.2f} / {r.goal_rate:.2f} (n={int(r.n)})")
        lines.append(f"| {labels.get(e, e)} | " + " | ".join(cells) + " |")
    return ("Cells: the ego's collision rate (share of episodes with a vehicle collision) / "
            "goal rate, pooled over environments.\n\n" + "\n".join(lines) + "\n")


def cross_play_heatmap(table: pd.DataFrame, out: Path, labels: dict) -> list[Path]:
    from eval.figures import COLUMN_IN, _plt, _save

    plt = _plt()
    allt = table[table["env"] == "all"]
    egos = algo_order(allt["ego"].unique())
    partners = [p for p in [*egos, "autopilot"] if p in set(allt["partner"])]
    t = allt.set_index(["ego", "partner"])
    fig, axes = plt.subplots(1, 2, figsize=(2 * COLUMN_IN, 0.35 * len(egos) + 1.4))
    for ax, (col, title, cmap) in zip(axes, [("collision_rate", "Ego collision rate", "Reds"),
                                             ("goal_rate", "Ego goal rate", "Greens")], strict=True):
        m = np.array([[t.loc[(e, p), col] for p in partners] for e in egos], float)
        ax.imshow(m, vmin=0, vmax=1, cmap=cmap, aspect="auto")
        for i in range(len(egos)):
            for j in range(len(partners)):
                ax.text(j, i, f"{m[i, j]:.2f}", ha="center", va="center", fontsize=6,
                        color="white" if m[i, j] > 0.6 else "black")
        ax.set_xticks(range(len(partners)))
        ax.set_xticklabels([labels.get(p, p) for p in partners], rotation=30, ha="right")
        ax.set_yticks(range(len(egos)))
        ax.set_yticklabels([labels.get(e, e) for e in egos])
        ax.set_xlabel("among (partner ACs)")
        ax.set_title(title)
    axes[0].set_ylabel("ego AC")
    fig.tight_layout()
    return _save(fig, Path(out), "crossplay_heatmap")


def run_sweep(plan, make_policy: Callable, algos: Sequence[str], kind: str, levels: Sequence[float],
              progress: Callable[[str], None] | None = None) -> pd.DataFrame:
    """Scenario 1 records at every level of one perturbation."""
    from cosim.scenario import load_scenario

    algos = list(algos)[: plan.agents]
    seeds = [plan.seed + e for e in range(plan.episodes)]
    frames = []
    for level in levels:
        for env_name in plan.envs:
            sc = load_scenario(env_name)
            if kind == "density":
                sc = sc.with_overrides(background=dataclasses.replace(
                    sc.background, scale=sc.background.scale * level))
            env = _env(sc, [_kind(a) for a in algos], plan.steps)
            try:
                names = dict(zip(env.possible_agents, algos, strict=True))
                policies = {}
                for i, a in enumerate(env.possible_agents):
                    p = make_policy(env, a, names[a])
                    if kind != "density":
                        p = Perturbed(p, env.action_space(a), kind, level, seed=plan.seed * 1000 + i)
                    policies[a] = p
                rec = run_episodes(env, policies, seeds, algorithms=names)
            finally:
                env.close()
            frames.append(rec.assign(env=env_name, scenario=1, sweep=kind, level=float(level)))
            if progress:
                progress(f"{env_name} {kind}={level}")
    return pd.concat(frames, ignore_index=True)


def sweep_table(records: pd.DataFrame, dt: float | None = None) -> pd.DataFrame:
    """Per (level, algorithm, metric), pooled over environments: mean, 95% CI, n."""
    rows = []
    for level, g in records.groupby("level", sort=True):
        per = per_episode(g.drop(columns=["sweep", "level"]), dt)
        for algo, sub in per.groupby("algorithm", sort=False):
            for m, _ in SWEEP_METRICS:
                mean, lo, hi, n = bootstrap_ci(sub[m].to_numpy())
                rows.append({"sweep": records["sweep"].iloc[0], "level": level, "algorithm": algo,
                             "metric": m, "mean": mean, "ci_low": lo, "ci_high": hi, "n": n})
    return pd.DataFrame(rows)


def sweep_figure(table: pd.DataFrame, out: Path, labels: dict) -> list[Path]:
    from eval.figures import PAGE_IN, _legend, _plt, _save, colour

    plt = _plt()
    kind = table["sweep"].iloc[0]
    algos = algo_order(table["algorithm"].unique())
    fig, axes = plt.subplots(1, len(SWEEP_METRICS), figsize=(PAGE_IN, 1.9), squeeze=False)
    for ax, (m, name) in zip(axes[0], SWEEP_METRICS, strict=True):
        for a in algos:
            g = table[(table["metric"] == m) & (table["algorithm"] == a)].sort_values("level")
            ax.plot(g["level"], g["mean"], "o-", color=colour(a), lw=0.9, ms=2.5)
            ax.fill_between(g["level"], g["ci_low"], g["ci_high"], color=colour(a), alpha=0.15, lw=0)
        if m in ("safety", "lane_keeping"):
            ax.set_ylim(-0.05, 1.05)
        ax.set_xlabel(kind.replace("_", " "))
        ax.set_ylabel(name)
        ax.grid(lw=0.3)
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    _legend(fig, algos, labels, ncol=6)
    return _save(fig, Path(out), f"sweep_{kind}")


def sweep_markdown(table: pd.DataFrame, labels: dict) -> str:
    kind = table["sweep"].iloc[0]
    algos = algo_order(table["algorithm"].unique())
    lines = [f"| {kind} | metric | " + " | ".join(labels.get(a, a) for a in algos) + " |",
             "|---|---|" + "---|" * len(algos)]
    t = table.set_index(["level", "metric", "algorithm"])
    for level in sorted(table["level"].unique()):
        for m, _ in SWEEP_METRICS:
            cells = []
            for a in algos:
                r = t.loc[(level, m, a)]
                cells.append("-" if r.n == 0 else
                             f"{r['mean']:.2f} ± {max(r.ci_high - r['mean'], r['mean'] - r.ci_low):.2f}")
            lines.append(f"| {level:g} | {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write(out: Path, labels: dict, cross: pd.DataFrame | None = None,
          sweeps: dict[str, pd.DataFrame] | None = None) -> tuple[list[Path], str]:
    """Tables and figures of cross-play and sweeps; (files, Markdown for the index)."""
    out = Path(out)
    written, md = [], []
    if cross is not None and not cross.empty:
        table = cross_play_table(cross)
        table.to_csv(out / "crossplay.csv", index=False)
        text = cross_play_markdown(table, labels)
        (out / "crossplay.md").write_text(text)
        figs = cross_play_heatmap(table, out, labels)
        written += [out / "crossplay.csv", out / "crossplay.md", *figs]
        md += ["\n## Cross-play (Scenario 1 conditions: the ego AC among ACs of one partner policy)\n",
               text, "\n![crossplay_heatmap](crossplay_heatmap.png) ([PDF](crossplay_heatmap.pdf))\n"]
    for kind, rec in (sweeps or {}).items():
        table = sweep_table(rec)
        table.to_csv(out / f"sweep_{kind}.csv", index=False)
        figs = sweep_figure(table, out, labels)
        written += [out / f"sweep_{kind}.csv", *figs]
        md += [f"\n## Robustness sweep: {kind} (Scenario 1 conditions, pooled over environments)\n",
               "Mean ± 95% bootstrap CI over episodes.\n", sweep_markdown(table, labels),
               f"\n![sweep_{kind}](sweep_{kind}.png) ([PDF](sweep_{kind}.pdf))\n"]
    return written, "\n".join(md)
