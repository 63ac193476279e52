"""Failure replays (issue 13): the first collision of each algorithm in each environment.

After the test protocol ran, :func:`capture` re-runs the episode of each
algorithm's first collision (same seed, same policies: the protocol is
deterministic) and, around the collision step (the TTFC moment), keeps

- ``camera.gif``: that AC's camera from ``BEFORE`` steps (3 s) before to ``AFTER``
  steps (1 s) after the collision;
- ``overview.gif``: a top-down view centred on the AC over the same window;
- ``strip.png``: up to six moments of both (camera above overview), the step
  before the collision and the collision step among them, each labelled with its time
  from the collision (for papers and READMEs);
- ``state.xml``: the SUMO state at the collision step (``simulation.saveState``);
- ``state.json``: what the state holds (every vehicle and person position), the
  scenario, seed, episode and step, and whether the re-run reproduced the record (and, when
  not, ``why``: no collision at that step, or how far the AC was from its recorded position).

``cosim replay <state.json>`` (:func:`reload`) starts the scenario's SUMO, loads
the state and prints the positions it holds next to the saved ones; ``--plot``
draws them. sumo-gui opens the same state: ``sumo-gui -n <net> --load-state state.xml``.
"""

from __future__ import annotations

import json
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

if TYPE_CHECKING:
    from eval.testing.protocol import ProtocolPlan

BEFORE = 30   # steps (3 s at dt 0.1)
AFTER = 10    # steps (1 s)
OVERVIEW_PX = 168
OVERVIEW_EXTENT_M = 50.0
KINDS = (("collision_vehicle", "vehicle"), ("collision_pedestrian", "pedestrian"),
         ("collision_object", "object"))


def first_collisions(records: pd.DataFrame) -> pd.DataFrame:
    """Per (scenario, env, algorithm): the first collision of the test (earliest episode,
    then its first collision step), with its agent, seed and kind."""
    hits = records[records["collision"]].sort_values(["scenario", "env", "algorithm", "episode", "step"])
    first = hits.groupby(["scenario", "env", "algorithm"], sort=True).head(1)
    rows = []
    for r in first.itertuples(index=False):
        kind = next((name for col, name in KINDS if getattr(r, col, False)), "other")
        rows.append({"scenario": int(r.scenario), "env": r.env, "algorithm": r.algorithm,
                     "agent": r.agent, "episode": int(r.episode), "seed": int(r.seed),
                     "step": int(r.step), "x": float(r.x), "y": float(r.y), "kind": kind})
    return pd.DataFrame(rows)


def sumo_positions(ls) -> dict:
    """Every vehicle and person in the running SUMO: id -> [x, y, angle]."""
    veh = {v: [*map(float, ls.vehicle.getPosition(v)), float(ls.vehicle.getAngle(v))]
           for v in ls.vehicle.getIDList()}
    per = {p: [*map(float, ls.person.getPosition(p)), float(ls.person.getAngle(p))]
           for p in ls.person.getIDList()}
    return {"vehicles": veh, "persons": per, "time": float(ls.simulation.getTime())}


def reruns(records: pd.DataFrame) -> int:
    """How many episodes :func:`capture` re-runs (and calls its ``progress`` for)."""
    targets = first_collisions(records)
    if targets.empty:
        return 0
    return sum(1 if scenario == 1 else len(group)
               for (scenario, _, _), group in targets.groupby(["scenario", "env", "episode"]))


def capture(plan: ProtocolPlan, make_policy: Callable, algos: Sequence[str], records: pd.DataFrame, out: Path,
            labels: dict | None = None, progress: Callable[[str], None] | None = None) -> list[dict]:
    """Clips and SUMO states of every first collision (module docstring); one dict each."""
    from eval.labels import env_title
    from eval.testing.conditions import TestConditions, action_kinds
    from eval.testing.protocol import slot_order
    from eval.testing.rollout import _act

    labels = labels or {}
    algos = list(algos)[: plan.agents] if 1 in plan.scenarios else list(algos)
    targets = first_collisions(records)
    done: list[dict] = []
    if targets.empty:
        return done
    out = Path(out)
    # one re-run per (scenario, env, episode[, algorithm alone]) covers all its targets
    for (scenario, env_name, _episode), group in targets.groupby(["scenario", "env", "episode"], sort=True):
        runs = [group] if scenario == 1 else [group[group["algorithm"] == a] for a in group["algorithm"]]
        for sub in runs:
            env_algos = (slot_order(algos, int(_episode), plan.rotate) if scenario == 1
                         else [sub["algorithm"].iloc[0]])
            env = TestConditions.of(int(scenario), plan.steps).env(env_name, action_kinds(env_algos))
            try:
                agent_algo = dict(zip(env.possible_agents, env_algos, strict=True))
                policies = {a: make_policy(env, a, agent_algo[a]) for a in env.possible_agents}
                want = {(r.agent if scenario == 1 else "ac_0"): r for r in sub.itertuples(index=False)}
                done += _rerun(env, policies, want, int(sub["seed"].iloc[0]), int(scenario),
                               env_name, env_title(env_name), agent_algo, labels, out, _act)
            finally:
                env.close()
            if progress:
                progress(f"{env_name} scenario {scenario} replay")
    return sorted(done, key=lambda r: (r["scenario"], r["env"], r["algorithm"]))


def _rerun(env, policies, want, seed, scenario, env_name, title, agent_algo, labels, out, act):
    from cosim.viz import mosaic, save_gif, save_png, upscale

    obs, _ = env.reset(seed=seed)
    for p in policies.values():
        if hasattr(p, "reset"):
            p.reset()
    last_step = max(r.step for r in want.values()) + AFTER
    first_step = min(r.step for r in want.values()) - BEFORE
    cams = {a: deque(maxlen=BEFORE + AFTER + 1) for a in want}
    tops = {a: deque(maxlen=BEFORE + AFTER + 1) for a in want}
    saved: dict[str, dict] = {}
    step = 0
    while env.agents and step < last_step:
        actions = {a: act(policies[a], obs[a]) for a in env.agents}
        obs, _, _, _, infos = env.step(actions)
        step += 1
        if step < first_step:
            continue
        for a, r in want.items():
            if not r.step - BEFORE <= step <= r.step + AFTER or a not in obs:
                continue
            cams[a].append(upscale(obs[a], 2))
            x, y, _, _ = env.world.ac_state(a)
            tops[a].append(env.mirror.overview((OVERVIEW_PX, OVERVIEW_PX), center=(x, y),
                                               extent=OVERVIEW_EXTENT_M))
            if step == r.step:
                algo = agent_algo[a]
                folder = out / "replays" / f"s{scenario}_{env_name}_{algo}"
                folder.mkdir(parents=True, exist_ok=True)
                ls = env.world.bridge._ls
                ls.simulation.saveState(str(folder / "state.xml"))
                info = infos.get(a, {})
                off = float(np.hypot(info.get("x", np.nan) - r.x, info.get("y", np.nan) - r.y))
                reproduced = bool(info.get("collision")) and off < 1e-6
                why = ("" if reproduced else
                       f"the re-run had no collision at step {int(r.step)}" if not info.get("collision")
                       else f"the re-run's AC was {off:.2f} m from the recorded position at the "
                            "collision step")
                meta = {
                    "scenario": scenario, "env": env_name, "title": title, "algorithm": algo,
                    "label": labels.get(algo, algo), "agent": a, "episode": int(r.episode),
                    "seed": seed, "step": int(r.step), "ttfc": round(r.step * env.scenario.dt, 6),
                    "kind": r.kind, "hit": str(info.get("hit", "")), "ac_xy": [r.x, r.y],
                    "reproduced": reproduced, "why": why, "state": "state.xml",
                    "background": scenario == 1, "pedestrians": scenario == 1,
                    "positions": sumo_positions(ls),
                }
                (folder / "state.json").write_text(json.dumps(meta, indent=1))
                saved[a] = {"folder": folder, "meta": meta, "index": len(cams[a]) - 1}
    rows = []
    for a, s in saved.items():  # index: the collision's frame in the clip
        folder, meta, k = s["folder"], s["meta"], s["index"]
        save_gif(folder / "camera.gif", list(cams[a]))
        save_gif(folder / "overview.gif", list(tops[a]))
        # four moments spread over the clip, plus the step before the collision and its step
        spread = np.linspace(0, len(cams[a]) - 1, 4).round().astype(int).tolist()
        picks = sorted(set(spread) | {max(k - 1, 0), k})
        dt = env.scenario.dt
        pairs = [labelled(np.concatenate([cams[a][i], tops[a][i]], axis=0),
                          "collision" if i == k else f"{(i - k) * dt:+.1f} s") for i in picks]
        save_png(folder / "strip.png", mosaic(pairs, cols=len(pairs)))
        rel = folder.relative_to(out).as_posix()
        rows.append({**{key: meta[key] for key in ("scenario", "env", "title", "algorithm", "label",
                                                   "agent", "episode", "step", "ttfc", "kind",
                                                   "reproduced", "why")},
                     "camera": f"{rel}/camera.gif", "overview": f"{rel}/overview.gif",
                     "strip": f"{rel}/strip.png", "state": f"{rel}/state.xml", "frame": k,
                     "meta": f"{rel}/state.json"})
    return rows


def labelled(frame: np.ndarray, text: str) -> np.ndarray:
    """``frame`` with a black band on top carrying ``text`` (a strip frame's time from the
    collision), drawn with Pillow's built-in font."""
    from PIL import Image, ImageDraw

    band = Image.new("RGB", (frame.shape[1], 12), (0, 0, 0))
    ImageDraw.Draw(band).text((3, 0), text, fill=(255, 255, 255))
    return np.concatenate([np.asarray(band, np.uint8), np.asarray(frame, np.uint8)], axis=0)


def reload(meta_path: Path) -> dict:
    """Start the scenario's SUMO, load the saved state; the positions it holds now
    and the largest distance (m) from the saved ones."""
    from cosim.scenario import load_scenario
    from cosim.sumo_bridge import SumoBridge

    meta_path = Path(meta_path)
    if meta_path.suffix == ".xml":
        meta_path = meta_path.with_suffix(".json")
    meta = json.loads(meta_path.read_text())
    bridge = SumoBridge(load_scenario(meta["env"]), background=meta["background"],
                        pedestrians=meta["pedestrians"])
    try:
        bridge.start(int(meta["seed"]))
        bridge._ls.simulation.loadState(str(meta_path.parent / meta["state"]))
        now = sumo_positions(bridge._ls)
    finally:
        bridge.close()
    saved = meta["positions"]
    worst = 0.0
    for kind in ("vehicles", "persons"):
        for vid, p in saved[kind].items():
            q = now[kind].get(vid)
            worst = max(worst, float("inf") if q is None else float(np.hypot(p[0] - q[0], p[1] - q[1])))
    return {"meta": meta, "positions": now, "max_deviation_m": worst}


def plot(result: dict, path: Path) -> Path:
    """The reloaded positions (cars blue, the collided AC red, other ACs orange, people green)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    meta, pos = result["meta"], result["positions"]
    fig, ax = plt.subplots(figsize=(4, 4))
    for vid, (x, y, _) in pos["vehicles"].items():
        c = "red" if vid == meta["agent"] else "orange" if vid.startswith("ac_") else "tab:blue"
        ax.plot(x, y, "s", color=c, ms=5)
        if vid.startswith("ac_"):
            ax.annotate(vid, (x, y), fontsize=6)
    for x, y, _ in pos["persons"].values():
        ax.plot(x, y, "o", color="green", ms=3)
    ax.set_aspect("equal")
    ax.set_title(f"{meta['title']} S{meta['scenario']} {meta['label']}: t={meta['ttfc']:.1f} s", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=150)
    plt.close(fig)
    return Path(path)
