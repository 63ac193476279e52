"""SUMO-side throughput: World.step() (dynamics + SUMO + snapshot + events + reward), no rendering.

Runs env_3 (signalised four-way with pedestrians) with 1, 3 and 6 learning cars
driven by a fixed cheap policy (throttle with a gentle random steer, so the
policy itself costs nothing), resetting whenever every AC is done; resets are not
timed. Prints steps/s (median of repeats) and the time split per phase; then, with 6 ACs, the
cost of the junction gate (``SumoBridge.gate_entries``: SUMO's cars and people wait for
an AC on their path): the same runs with the gate switched off, interleaved on/off.
With ``--cars-see``, only the cost of ``Scenario.cars_see_acs`` (SUMO's cars and people stop
for an AC's body anywhere on their path; on by default): 6 ACs with it on and off, interleaved.

    python bench/sumo_side.py [--steps 3000] [--repeats 3] [--cars-see]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from cosim.scenario import load_scenario
from cosim.sumo_bridge import SumoBridge
from cosim.world import World


def run(num_acs: int, steps: int, seed: int,
        cars_see_acs: bool | None = None) -> tuple[float, dict[str, float]]:
    rng = np.random.default_rng(seed)
    phases = {"dynamics": 0.0, "sumo": 0.0, "snapshot": 0.0, "events": 0.0}
    scenario = load_scenario("env_3")
    if cars_see_acs is not None:  # else the scenario's own (on)
        scenario = scenario.with_overrides(cars_see_acs=cars_see_acs)
    with World(scenario, num_acs) as w:
        w.reset(seed=seed)
        done = 0
        elapsed = 0.0
        while done < steps:
            if not w.active:
                for k in phases:
                    phases[k] += getattr(w.times, k)
                w.reset(seed=seed + done)
            controls = {a: (0.6, float(rng.normal(0, 0.05))) for a in w.active}
            t0 = time.perf_counter()
            w.step(controls)
            elapsed += time.perf_counter() - t0
            done += 1
        for k in phases:
            phases[k] += getattr(w.times, k)
    return steps / elapsed, {k: 1e3 * v / steps for k, v in phases.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--cars-see", action="store_true",
                        help="only 6 ACs with Scenario.cars_see_acs on and off, interleaved")
    args = parser.parse_args()
    if args.cars_see:
        cars_see_cost(args.steps, args.repeats)
        return
    print("| ACs | steps/s (median) | dynamics ms | SUMO ms | snapshot ms | events+reward ms |")
    print("|---|---|---|---|---|---|")
    for n in (1, 3, 6):
        runs = [run(n, args.steps, seed=10 + r) for r in range(args.repeats)]
        rates = [r[0] for r in runs]
        best = sorted(runs, key=lambda r: r[0])[len(runs) // 2]
        ph = best[1]
        print(f"| {n} | {statistics.median(rates):.0f} | {ph['dynamics']:.3f} | {ph['sumo']:.3f} | "
              f"{ph['snapshot']:.3f} | {ph['events']:.3f} |")
    gate_cost(args.steps, args.repeats)


def gate_cost(steps: int, repeats: int) -> None:
    """6 ACs with the junction gate on and off, interleaved; medians and their ratio."""
    gate = SumoBridge.gate_entries
    rates: dict[str, list[float]] = {"on": [], "off": []}
    try:
        for r in range(repeats):
            for mode in ("on", "off"):
                SumoBridge.gate_entries = gate if mode == "on" else (lambda self, *a: None)
                rates[mode].append(run(6, steps, seed=10 + r)[0])
    finally:
        SumoBridge.gate_entries = gate
    on, off = statistics.median(rates["on"]), statistics.median(rates["off"])
    print("\n| 6 ACs | steps/s (median) |\n|---|---|")
    print(f"| gate on | {on:.0f} |\n| gate off | {off:.0f} |\n| on / off | {on / off:.2f} |")


def cars_see_cost(steps: int, repeats: int) -> None:
    """6 ACs with Scenario.cars_see_acs on and off, interleaved; medians and their ratio."""
    rates: dict[bool, list[float]] = {True: [], False: []}
    for r in range(repeats):
        for see in (True, False):
            rates[see].append(run(6, steps, seed=10 + r, cars_see_acs=see)[0])
    on, off = statistics.median(rates[True]), statistics.median(rates[False])
    print("| 6 ACs | steps/s (median) |\n|---|---|")
    print(f"| cars_see_acs on | {on:.0f} |\n| cars_see_acs off | {off:.0f} |\n| on / off | {on / off:.2f} |")
    print("runs (on):", " ".join(f"{x:.0f}" for x in rates[True]))
    print("runs (off):", " ".join(f"{x:.0f}" for x in rates[False]))


if __name__ == "__main__":
    main()
