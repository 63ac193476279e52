"""Names the reports share: the algorithms' order, the scenarios' names, environment titles.

Its own module so that ``eval/figures.py`` and ``eval/report.py`` (which draws the figures)
both import it instead of each other: no import cycle (tests/eval/test_layout.py).
``eval.report`` re-exports these names.
"""

from __future__ import annotations

ALGO_ORDER = ("ppo", "a3c", "impala", "dqn", "ddpg", "td3")
SCENARIO_NAMES = {1: "Scenario 1 (multi-agent)", 2: "Scenario 2 (single-agent)"}


def algo_order(names) -> list[str]:
    """``names`` in the paper's algorithm order, anything else after it, sorted."""
    names = set(names)
    return [a for a in ALGO_ORDER if a in names] + sorted(names - set(ALGO_ORDER))


def env_title(env: str) -> str:
    """The environment's title from its scenario YAML (Straight, ...), else its name."""
    try:
        from cosim.scenario import load_scenario

        return load_scenario(env).title or env
    except Exception:  # noqa: BLE001 - a report must not fail on a title
        return env
