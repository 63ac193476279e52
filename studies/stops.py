"""Where each AC stopped for good: one row per (report, episode, AC) of `cosim test` reports.

A diagnostic for the turning slots (issue 27, target 2): a goal rate of 0 says that a slot
fails, not how. From each report's per-step records (``records.parquet``) this prints, per
AC-episode: whether it reached its goal, the last step it was still moving, how far it got
(DISTANCE, the test's metric) and how much of its route was left at the end, its steps off the road and
on a wrong lane, its contact steps, the reward's charge for them and its return; then one summary
line per policy and slot, and one per policy with its mean return without the contact charge.
Contact steps are split by what held them: ``AC contacts`` are vehicle contacts with another AC's
centre within :data:`AC_CONTACT_M` that is in a vehicle contact at the same step (two learning
cars touching; an AC beside one that touches a background car is not counted), ``standing contacts`` are contact
steps of any kind below :data:`MOVING` (a car that stays in contact instead of driving out of it).
``--long N`` also lists every unbroken run of N or more contact steps of one AC (:func:`contact_runs`):
when it began, how it ended, which AC it was held against and where that AC's centre was in this
one's frame (ahead, beside or behind: a car whose centre is behind this one's cannot be in its
forward camera), and what share of all contact steps such runs hold.

    cosim test --algos dqn --envs env_2 --scenario 2 --episodes 6 --steps 600 --seed 10000 \\
        --runs grid27/runs --references none --out s2/dqn
    python studies/stops.py s2/dqn/* s2/td3/* --out episodes.csv
    python studies/stops.py arms/records/demo.parquet   # `studies/arms.py`'s records work too
    python studies/stops.py science/test/*.parquet --long 50 --runs-out runs.csv
    python studies/stops.py sci_2s1/test/*.parquet --policy-out docs/results/<page>/study/contact.csv

A report of a reference driver (``cosim test --policy autopilot``) is labelled with the
driver's name (its provenance.json), a report of trained checkpoints with the algorithm.
Results: task version 3; in git history at 1b59d82, docs/results/2026-11-26-turning-alone.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from eval.testing.metrics import distance_driven

MOVING = 0.1
"""m/s: a step at this speed or more counts as moving."""

LONG = 50
"""Contact steps in one unbroken run that make a long run (the contact-runs page's ``--long 50``;
part pages and studies/variant_table.py count with it)."""

AC_CONTACT_M = 5.0
"""m between two ACs' centres within which a vehicle contact is counted as one with an AC: two
4.5 m x 1.8 m footprints (cosim/dynamics.py) can touch only closer than their diagonal, 4.85 m."""


def policy_label(report: Path, algorithm: str) -> str:
    """The reference driver's name for a reference report, else the algorithm."""
    prov = report / "provenance.json"
    policy = json.loads(prov.read_text()).get("policy", "trained") if prov.exists() else "trained"
    return algorithm if policy == "trained" else policy


def _runs(records: pd.DataFrame):
    """The records of each simulation run: one (training seed, scenario, episode) of ACs driving
    together, or, where one (step, agent) occurs more than once there (Scenario 2 of a study's
    records: each algorithm's AC alone, in its own environment), one (..., algorithm)."""
    keys = [k for k in ("train_seed", "scenario", "episode") if k in records]
    for _key, g in records.groupby(keys, sort=False):
        if g.duplicated(["step", "agent"]).any():
            yield from (run for _a, run in g.groupby("algorithm", sort=False))
        else:
            yield g


def nearest_ac(records: pd.DataFrame) -> pd.Series:
    """Per record row: metres from this AC's centre to the nearest other AC's that is in a vehicle
    contact at the same step of the same run (:func:`_runs`); infinite where there is none."""
    out = pd.Series(np.inf, index=records.index)
    for g in _runs(records):
        x = g.pivot(index="step", columns="agent", values="x")
        y = g.pivot(index="step", columns="agent", values="y")
        if x.shape[1] < 2:
            continue
        touching = g.pivot(index="step", columns="agent", values="collision_vehicle").fillna(False)
        d = np.hypot(x.values[:, :, None] - x.values[:, None, :], y.values[:, :, None] - y.values[:, None, :])
        d[~touching.to_numpy(dtype=bool)[:, None, :].repeat(d.shape[1], axis=1)] = np.inf
        idx = np.arange(d.shape[1])
        d[:, idx, idx] = np.inf
        near = pd.DataFrame(np.fmin.reduce(d, axis=2), index=x.index, columns=x.columns)  # NaN: AC gone
        pairs = near.stack().rename("near")
        keyed = g[["step", "agent"]].join(pairs, on=["step", "agent"])
        out.loc[g.index] = keyed["near"].fillna(np.inf).values
    return out


BESIDE_M = 1.0
"""m: another AC whose centre is within this distance of this AC's centre along its heading is
*beside* it; further forward it is *ahead*, further back *behind*."""


def _bearing(me: pd.Series, other: pd.Series) -> tuple[str, float]:
    """Where ``other``'s centre lies in ``me``'s frame ("ahead", "beside", "behind") and how far
    along ``me``'s heading (metres, + ahead); headings are radians from +x, counter-clockwise."""
    along = float((other.x - me.x) * np.cos(me.heading) + (other.y - me.y) * np.sin(me.heading))
    side = "ahead" if along > BESIDE_M else "behind" if along < -BESIDE_M else "beside"
    return side, round(along, 1)


def contact_runs(records: pd.DataFrame, min_steps: int = 1) -> pd.DataFrame:
    """One row per unbroken run of ``min_steps`` or more contact steps (a car, an object or a
    pedestrian) of one AC in one simulation run: its policy, slot, first step and length, what it
    touched at the first step (``with``: car, object or pedestrian) and whether it was off its
    lane then (off the road or on a wrong lane: SUMO's cars do not see such an AC), the share of
    it standing, how it ended (``left`` the contact, ``goal``, or the episode's ``end``), and the
    other AC it was held against where one in a vehicle contact had its centre within
    :data:`AC_CONTACT_M` at the run's first step (``partner``, that AC's policy, its bearing from
    this AC and this AC's from it and both speeds at the first step: who drove into whom; its
    bearing at the run's last step: what this AC's camera could see while it stood); ``partner``
    is empty for a contact with a background car or object."""
    rows = []
    for g in _runs(records):
        g = g.sort_values(["agent", "step"])
        by_step = {a: h.set_index("step") for a, h in g.groupby("agent", sort=False)}
        for agent, h in by_step.items():
            contact = (h.collision_vehicle | h.collision_object | h.get("collision_pedestrian", False)).to_numpy()
            edges = np.flatnonzero(np.diff(np.concatenate([[0], contact.astype(int), [0]])))
            for start, stop in zip(edges[::2], edges[1::2], strict=True):
                if stop - start < min_steps:
                    continue
                steps = h.index[start:stop]
                first, last = h.loc[steps[0]], h.loc[steps[-1]]
                ended = "goal" if last.goal_reached else "end" if stop == len(h) else "left"
                row = {"policy": str(h.algorithm.iloc[0]), "env": str(h.env.iloc[0]),
                       "scenario": int(h.scenario.iloc[0]) if "scenario" in h else -1,
                       "episode seed": int(h.seed.iloc[0]), "agent": agent, "first step": int(steps[0]),
                       "steps": int(stop - start), "standing": round(float((h.speed.loc[steps] < MOVING).mean()), 2),
                       "ended": ended, "speed at first": round(float(first.speed), 1),
                       "with": ("car" if first.collision_vehicle else "object" if first.collision_object
                                else "pedestrian"),
                       "off lane at first": bool(first.off_road or first.wrong_lane),
                       "partner": "", "partner policy": "", "partner at": "", "partner along m": np.nan,
                       "seen from partner": "", "partner speed at first": np.nan, "partner at last": ""}
                others = [(float(np.hypot(o.loc[steps[0]].x - first.x, o.loc[steps[0]].y - first.y)), b)
                          for b, o in by_step.items() if b != agent and steps[0] in o.index
                          and o.loc[steps[0]].collision_vehicle]
                if others and min(others)[0] <= AC_CONTACT_M and first.collision_vehicle:
                    b = min(others)[1]
                    other = by_step[b].loc[steps[0]]
                    row.update({"partner": b, "partner policy": str(other.algorithm),
                                "partner speed at first": round(float(other.speed), 1),
                                "seen from partner": _bearing(other, first)[0]})
                    row["partner at"], row["partner along m"] = _bearing(first, other)
                    if steps[-1] in by_step[b].index:
                        row["partner at last"] = _bearing(last, by_step[b].loc[steps[-1]])[0]
                rows.append(row)
    return pd.DataFrame(rows)


def runs_summary(runs: pd.DataFrame, all_contact_steps: int) -> pd.DataFrame:
    """How much of all contact steps the runs hold: per partner kind (another AC, by where it
    stood; else what the AC touched at the run's first step: a background car, an object or a
    pedestrian) the runs, their steps, the runs that lasted to the episode's end, the mean share
    standing, the steps of runs that began with the AC off its lane, and the share of all contact
    steps."""
    kind = np.where(runs["partner"] == "", np.where(runs["with"] == "car", "background car", runs["with"]),
                    "AC " + runs["partner at"].astype(str))
    off = runs["steps"].where(runs["off lane at first"], 0)
    out = runs.assign(kind=kind, to_end=runs["ended"] == "end", off=off).groupby("kind").agg(
        runs=("steps", "size"), steps=("steps", "sum"), to_end=("to_end", "sum"),
        standing=("standing", "mean"), steps_off_lane=("off", "sum"))
    out["share_of_all_contact"] = out["steps"] / max(all_contact_steps, 1)
    return out.round(2).reset_index()


def load_records(report: Path) -> pd.DataFrame:
    """A `cosim test` report folder's records.parquet, or a records parquet file itself."""
    report = Path(report)
    path = report if report.suffix == ".parquet" else report / "records.parquet"
    if not path.exists():
        raise SystemExit(f"stops: {report} has no records.parquet; give a `cosim test` report folder "
                         "or a records .parquet file")
    return pd.read_parquet(path)


def episode_rows(report: Path) -> pd.DataFrame:
    """One row per (scenario, episode, AC, algorithm) of one `cosim test` report folder (or records
    file): a study's records hold Scenario 1 and each algorithm's Scenario 2 runs, episode numbers alike."""
    records = load_records(report)
    records = records.assign(near_ac=nearest_ac(records))
    folder = Path(report) if Path(report).suffix != ".parquet" else Path(report).parent
    rows = []
    keys = [k for k in ("train_seed", "scenario", "episode", "agent", "algorithm") if k in records]
    for _key, g in records.groupby(keys, sort=True):  # a study's records hold both scenarios
        agent = str(g.agent.iloc[0])
        g = g.sort_values("step")
        moving = g.loc[g.speed >= MOVING, "step"]
        end = g.iloc[-1]
        contact = g.collision_vehicle | g.collision_object | g.get("collision_pedestrian", False)
        rows.append({
            "policy": policy_label(folder, str(g.algorithm.iloc[0])),
            "env": str(g.env.iloc[0]), "scenario": int(g.scenario.iloc[0]),
            **({"train seed": int(g.train_seed.iloc[0])} if "train_seed" in g else {}),
            "agent": agent,
            "episode seed": int(g.seed.iloc[0]), "goal": bool(g.goal_reached.any()),
            "steps": len(g), "last step moving": int(moving.max()) if len(moving) else 0,
            "driven m": round(distance_driven(g), 1),
            "route m left": round(float(end.distance_to_goal), 1),
            "steps off road": int(g.off_road.sum()), "steps wrong lane": int(g.wrong_lane.sum()),
            "object contacts": int(g.collision_object.sum()),
            "vehicle contacts": int(g.collision_vehicle.sum()),
            "AC contacts": int((g.collision_vehicle & (g.near_ac <= AC_CONTACT_M)).sum()),
            "contact steps": int(contact.sum()),
            "standing contacts": int((contact & (g.speed < MOVING)).sum()),
            "contact charge": round(float(g.r_collision.sum()), 1) if "r_collision" in g else np.nan,
            "return": round(float(g.reward.sum()), 1)})
    return pd.DataFrame(rows)


def summary(rows: pd.DataFrame) -> pd.DataFrame:
    """Per (policy, environment, scenario, slot): episodes, goal rate, mean return, mean
    distance driven, median last moving step, mean route left at the end, the
    episodes that stood still for their last 100 steps or more without a goal, mean contact
    steps, and the shares of those with another AC and standing."""
    stood = (rows["steps"] - rows["last step moving"] >= 100) & ~rows["goal"]
    keys = ["policy", "env", "scenario", "agent"]
    out = rows.assign(stood=stood).groupby(keys, sort=False).agg(
        episodes=("goal", "size"), goal_rate=("goal", "mean"), mean_return=("return", "mean"),
        driven_m=("driven m", "mean"), last_moving_median=("last step moving", "median"),
        route_left_m=("route m left", "mean"), stood_still=("stood", "sum"),
        contact_steps=("contact steps", "mean"), ac=("AC contacts", "sum"),
        standing=("standing contacts", "sum"), all_contacts=("contact steps", "sum"))
    total = out.pop("all_contacts").where(lambda c: c > 0)
    out["AC_share"] = out.pop("ac") / total
    out["standing_share"] = out.pop("standing") / total
    return out.round(2).reset_index()


def by_policy(rows: pd.DataFrame) -> pd.DataFrame:
    """Per (policy, environment, scenario and, for a science study's records, training seed),
    over its AC-episodes: the mean return, the mean return without the contact steps' charge
    (the reward's collision term), all contact steps and the shares of those with another AC
    and standing: how much of a mean the contact sets."""
    keys = ["policy", "env", "scenario", *(["train seed"] if "train seed" in rows else [])]
    out = rows.assign(without=rows["return"] - rows["contact charge"]).groupby(keys, sort=False, dropna=False).agg(
        ac_episodes=("goal", "size"), goal_rate=("goal", "mean"), mean_return=("return", "mean"),
        without_contact_charge=("without", "mean"), contact_steps=("contact steps", "sum"),
        ac=("AC contacts", "sum"), standing=("standing contacts", "sum"))
    total = out["contact_steps"].where(lambda c: c > 0)
    out["AC_share"] = out.pop("ac") / total
    out["standing_share"] = out.pop("standing") / total
    return out.round(2).reset_index()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("reports", nargs="+", type=Path, help="`cosim test` report folders or records .parquet files")
    p.add_argument("--out", type=Path, default=None, help="also write the episode rows as CSV")
    p.add_argument("--long", type=int, default=0, metavar="N",
                   help="also list every unbroken run of N or more contact steps of one AC and what held it")
    p.add_argument("--runs-out", type=Path, default=None, help="with --long: also write those runs as CSV")
    p.add_argument("--policy-out", type=Path, default=None,
                   help="also write the per-policy lines (mean return without the contact charge) as CSV: "
                        "a science study part's contact.csv, which studies/contact_table.py reads")
    args = p.parse_args(argv)
    if args.long < 0:
        raise SystemExit(f"stops: --long {args.long} is negative; give a number of contact steps, e.g. --long 50")
    rows = pd.concat([episode_rows(r) for r in args.reports], ignore_index=True)
    if args.out:
        rows.to_csv(args.out, index=False)
    print(rows.to_string(index=False))
    print()
    print(summary(rows).to_string(index=False))
    print()
    per_policy = by_policy(rows)
    if args.policy_out:
        per_policy.to_csv(args.policy_out, index=False)
    print(per_policy.to_string(index=False))
    if args.long:
        runs = pd.concat([contact_runs(load_records(r), args.long) for r in args.reports], ignore_index=True)
        if args.runs_out:
            runs.to_csv(args.runs_out, index=False)
        print()
        if runs.empty:
            print(f"no run of {args.long} or more contact steps")
        else:
            print(runs.sort_values("steps", ascending=False).to_string(index=False))
            print()
            print(runs_summary(runs, int(rows["contact steps"].sum())).to_string(index=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
