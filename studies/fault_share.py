"""Who is charged for a vehicle contact: how many of the collision events an AC is charged under
``Contact.fault: both`` (the default) it did not cause (docs/task.md, "Collision rule").

    python studies/fault_share.py --envs env_2 env_4 --episodes 4 --noise 0.3 --out fault.csv

Six ACs drive the autopilot with a share ``--noise`` of their steps replaced by a uniformly random
discrete action (an exploring learner's mistakes, the autopilot's driving otherwise), in traffic,
on held-out seeds (10,000, ...), under the default rule. Each vehicle collision event an AC is
charged is classed as the AC's fault (it moved at >= 0.5 m/s and the other's centre lay ahead of
its own: what ``fault: at_fault`` charges) or not (it stood, or was hit from behind), and by the
other party (another AC or a SUMO car). Prints one row per environment; ``--out`` writes them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from cosim.controller import Autopilot  # noqa: E402
from cosim.dynamics import discrete_controls  # noqa: E402
from cosim.events import PEDESTRIAN_MIN_SPEED  # noqa: E402
from cosim.world import World  # noqa: E402
from eval.testing.validity import HELD_OUT_SEED  # noqa: E402


def measure(env: str, episodes: int, noise: float, agents: int = 6, steps: int | None = None) -> dict:
    """Counts of the vehicle collision events charged to the ACs of ``env`` under the default rule."""
    counts = {"env": env, "episodes": episodes, "noise": noise, "events": 0, "at_fault": 0,
              "not_at_fault": 0, "with_ac": 0, "with_car": 0, "not_at_fault_with_ac": 0}
    with World(env, agents) as w:
        table = discrete_controls(w.vehicle)
        horizon = steps or w.scenario.horizon
        for ep in range(episodes):
            seed = HELD_OUT_SEED + ep
            rng = np.random.default_rng(seed)
            w.reset(seed=seed)
            pilots = {a: Autopilot(w, a) for a in w.ac_ids}
            for _ in range(horizon):
                if not w.active:
                    break
                act = {a: tuple(table[rng.integers(len(table))]) if rng.random() < noise
                       else tuple(pilots[a].act()) for a in w.active}
                before = {a: w.ac_state(a) for a in w.active}
                out = w.step(act)
                for a, r in out.items():
                    if not r.events.event_vehicle:
                        continue
                    i = w.index[a]
                    others = [o for k, o in r.events.touching if k == "vehicle"]
                    other = others[0] if others else ""
                    # the pose and speed after the AC's own move: before a blocked move was undone
                    moving = before[a][3] >= PEDESTRIAN_MIN_SPEED or r.events.speed >= PEDESTRIAN_MIN_SPEED
                    ahead = any(w._ahead(i, o) is not None for o in others)
                    fault = moving and ahead
                    counts["events"] += 1
                    counts["at_fault" if fault else "not_at_fault"] += 1
                    is_ac = other.startswith("ac_")
                    counts["with_ac" if is_ac else "with_car"] += 1
                    counts["not_at_fault_with_ac"] += int(is_ac and not fault)
    counts["share_not_at_fault"] = counts["not_at_fault"] / max(counts["events"], 1)
    return counts


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--envs", nargs="+", default=["env_2", "env_4"])
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--noise", type=float, default=0.3, help="share of random steps (default 0.3)")
    p.add_argument("--steps", type=int, default=None, help="steps per episode (default: horizon)")
    p.add_argument("--out", type=Path, default=None, help="CSV of the rows")
    args = p.parse_args(argv)
    if not 0.0 <= args.noise <= 1.0 or args.episodes < 1:
        p.error("--noise must be 0..1 and --episodes >= 1")
    rows = pd.DataFrame([measure(e, args.episodes, args.noise, steps=args.steps) for e in args.envs])
    print(rows.to_string(index=False))
    if args.out:
        rows.to_csv(args.out, index=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
