"""`cosim` commands that run the simulation without learning: scenarios, drive, view,
check-scenarios, nets (the parser is in eval/cli/__init__.py)."""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

from eval.training.runfolder import output_folder

EVENT_KEYS = (
    "collision_vehicle", "collision_pedestrian", "collision_object",
    "off_road", "wrong_lane", "red_light", "goal_reached",
)


def cmd_scenarios(args) -> int:
    from cosim.scenario import available_scenarios, load_scenario

    for name in available_scenarios():
        sc = load_scenario(name)
        peds = "pedestrians" if sc.pedestrians else "no pedestrians"
        print(f"{name:7s} {sc.title:11s} {sc.max_agents} ACs, {peds:14s} {sc.description}")
    return 0


def cmd_drive(args) -> int:
    import numpy as np
    from tqdm import tqdm

    from cosim.controller import Autopilot
    from cosim.world import World

    rng = np.random.default_rng(args.seed)
    counts: Counter = Counter()
    with World(args.scenario, args.agents, background=not args.no_background,
               pedestrians=not args.no_pedestrians,
               backend="gui" if args.gui else "auto") as world:
        world.reset(seed=args.seed)
        sc = world.scenario
        print(f"{sc.name} ({sc.title}): {world.num_acs} ACs, {args.steps} steps of {sc.dt} s, "
              f"seed {args.seed}, policy {args.policy}")
        pilots = {a: Autopilot(world, a) for a in world.ac_ids}
        final = {}
        bar = tqdm(range(args.steps), disable=args.quiet, unit="step", desc=sc.name)
        for step in bar:
            if not world.active:
                break
            if args.policy == "autopilot":
                controls = {a: tuple(pilots[a].act()) for a in world.active}
            else:
                controls = {a: tuple(rng.uniform(-1, 1, 2)) for a in world.active}
            for ac, res in world.step(controls).items():
                final[ac] = (step + 1, res.events.distance_to_goal,
                             _outcome(res.events.goal_reached, res.terminated, res.truncated))
                for key in EVENT_KEYS:
                    if getattr(res.events, key):
                        counts[(ac, key)] += 1
                        if key != "goal_reached" and counts[(ac, key)] == 1:
                            bar.write(f"  t={world.bridge.time:6.1f}s {ac}: {key}"
                                      + (f" ({res.events.hit})" if res.events.hit else ""))
        bar.close()
    _print_summary(world.ac_ids, final, counts)
    return 0


def _outcome(goal: bool, terminated: bool, truncated: bool) -> str:
    return "goal" if goal else "ended" if terminated else "truncated" if truncated else "running"


def _print_summary(ac_ids, final, counts) -> None:
    """`final`: AC -> (steps, metres to goal, outcome); `counts`: (AC, event) -> steps."""
    cols = ["vehicle", "pedestrian", "object", "off-road", "wrong lane", "red light"]
    print(f"\n{'AC':6s} {'steps':>5s} " + " ".join(f"{c:>10s}" for c in cols)
          + f" {'to goal m':>9s}  outcome")
    for ac in ac_ids:
        if ac not in final:
            continue
        steps, to_goal, outcome = final[ac]
        row = [counts[(ac, k)] for k in EVENT_KEYS[:6]]
        print(f"{ac:6s} {steps:5d} " + " ".join(f"{v:10d}" for v in row)
              + f" {to_goal:9.1f}  {outcome}")
    print("(event columns count the steps with that event)")


def cmd_view(args) -> int:
    import numpy as np
    from tqdm import tqdm

    from cosim.controller import Autopilot
    from cosim.viz import mosaic, save_gif, save_png, side_by_side
    from eval.testing.conditions import TestConditions

    output_folder(args.out, "--out")
    # the test's rules (collisions do not end the run), the scenario's horizon, the autopilot
    env = TestConditions(background=not args.no_background, pedestrians=not args.no_pedestrians).env(
        args.scenario, "continuous", args.agents, seed=args.seed, image_size=args.image_size,
        render_mode="rgb_array")
    counts: Counter = Counter()
    final = {}
    rng = np.random.default_rng(args.seed)
    try:
        obs, _ = env.reset(seed=args.seed)
        world = env.world
        pilots = {a: Autopilot(world, a) for a in world.ac_ids}
        moments = set(np.linspace(0, args.steps - 1, args.moments).astype(int).tolist())
        first = env.possible_agents[0]
        cam_frames, overview_frames, written = [], [], []
        last = dict(obs)
        for step in tqdm(range(args.steps), disable=args.quiet, unit="step", desc="view"):
            if not env.agents:
                break
            if args.policy == "autopilot":
                actions = {a: pilots[a].act() for a in env.agents}
            else:
                actions = {a: rng.uniform(-1, 1, 2).astype(np.float32) for a in env.agents}
            obs, _, terms, truncs, infos = env.step(actions)
            last.update(obs)
            for ac, info in infos.items():
                final[ac] = (step + 1, info["distance_to_goal"],
                             _outcome(info["goal_reached"], terms[ac], truncs[ac]))
                for key in EVENT_KEYS:
                    if info[key]:
                        counts[(ac, key)] += 1
            if first in obs:
                cam_frames.append(obs[first])
            if step % 2 == 0:
                overview_frames.append(env.render())
            if step in moments:
                cams = mosaic([last[a] for a in env.possible_agents], cols=3, scale=2)
                # a close top-down view of the feature, as tall as the camera mosaic
                top = env.mirror.overview((cams.shape[0], cams.shape[0]), extent=args.extent)
                written.append(save_png(args.out / f"mosaic_{step:04d}.png",
                                        side_by_side(cams, top)))
        written.append(save_gif(args.out / f"camera_{first}.gif",
                                [np.kron(f, np.ones((3, 3, 1), np.uint8)) for f in cam_frames]))
        written.append(save_gif(args.out / "overview.gif", overview_frames, fps=5))
    finally:
        env.close()
    _print_summary(env.possible_agents, final, counts)
    print("\nwrote:\n" + "\n".join(f"  {p}" for p in written))
    return 0


def cmd_check_scenarios(args) -> int:
    from tqdm import tqdm

    from cosim.errors import CosimError
    from cosim.scenario import load_scenario
    from eval.testing import validity

    if args.episodes < 1 or (args.steps is not None and args.steps < 1):
        raise CosimError("--episodes and --steps must be >= 1")
    scenarios = [load_scenario(s) for s in args.scenarios]  # fail on a bad name before running
    for sc in scenarios:
        if any(not 1 <= n <= sc.max_agents for n in args.agents):
            raise CosimError(f"--agents {args.agents}: scenario {sc.name!r} has 1..{sc.max_agents} "
                             "spawn points; pass counts in that range")
    if args.out:  # a place it cannot write fails now, not after the whole suite ran
        output_file(args.out, "--out")
    failed, frames = [], []
    for sc in scenarios:
        for n in args.agents:
            bar = tqdm(total=len(validity.POLICIES), desc=f"{sc.name} x{n}", leave=False,
                       disable=None)
            rows = validity.check_scenario(
                sc, n, args.episodes, args.steps,
                progress=lambda p, bar=bar: (bar.set_postfix_str(p), bar.update(0)),
            )
            bar.close()
            table = validity.summarize(rows)
            problems = validity.failures(table)
            title = f"{sc.name} ({sc.title or sc.description}), {n} ACs, {args.episodes} episodes"
            print(f"\n### {title}\n\n{validity.format_table(table)}\n\n{validity.score_line(table)}")
            print("valid" if not problems else "NOT VALID:\n  " + "\n  ".join(problems))
            failed += [f"{sc.name} x{n}: {p}" for p in problems]
            frames.append(rows.assign(scenario=sc.name, agents=n))
    if args.out:
        import pandas as pd

        from eval.training.runfolder import atomic_write

        args.out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(args.out, pd.concat(frames).to_csv(index=False))  # a full disk: a named error
        print(f"wrote {args.out}")
    if failed:
        print(f"\n{len(failed)} validity criteria failed", file=sys.stderr)
        return 1
    print("\nevery scenario passed the validity criteria")
    return 0


def output_file(path: Path, flag: str) -> Path:
    """Check now that the file `path` can be written (its folder is created and probed, the file
    itself, where it exists, must be a writable file), so a bad --out fails before any work."""
    import os

    from cosim.errors import OptionError
    from eval.training.runfolder import unwritable_reason

    if path.is_dir():
        raise OptionError(f"{flag} {path}: is a folder; name a file in it, e.g. {flag} {path / 'rows.csv'}")
    reason = unwritable_reason(path.parent)
    if reason:
        raise OptionError(f"{flag} {path}: cannot write there ({reason} in {path.parent}); choose "
                          f"another {flag}")
    if path.exists() and not os.access(path, os.W_OK):
        raise OptionError(f"{flag} {path}: cannot write there (the file is read-only); choose another {flag}")
    return path


def cmd_nets(args) -> int:
    from cosim import nets

    configs = args.config or nets.default_configs()
    if args.action == "build":
        for cfg in configs:
            out = nets.build(cfg)
            print(f"built {out}")
        return 0
    nets.check(configs)
    print(f"up to date: {', '.join(str(c) for c in configs)}")
    return 0
