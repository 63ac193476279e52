"""How the reports present algorithms and environments: the algorithms' order and colours,
the scenarios' names, the environments' titles and colours, and the environment list.

The facts themselves have one source each: the algorithms and their order are the catalogue's
(agents/registry.py), the environments are the scenario files (``sumo_nets/scenarios/*.yaml``,
:func:`cosim.scenario.available_scenarios`) with their titles. Only the presentation is
decided here, once for every report, figure and study.

Its own module so that ``eval/reporting/figures.py`` and ``eval/reporting/report.py`` (which draws the figures)
both import it instead of each other: no import cycle (tests/eval/test_layout.py).
``eval.reporting.report`` re-exports the names it used to define.
"""

from __future__ import annotations

from agents import registry
from cosim.scenario import available_scenarios

ALGO_ORDER: tuple[str, ...] = tuple(registry.ALGORITHMS)
"""The algorithms in the catalogue's (the paper's) order: report columns, legends."""
SCENARIO_NAMES = {1: "Scenario 1 (multi-agent)", 2: "Scenario 2 (single-agent)"}
ENVS: tuple[str, ...] = tuple(available_scenarios())
"""The bundled environments, from the scenario files: the default of every command and
study that runs "all the environments"."""

COLOURS = {"ppo": "#0072B2", "a3c": "#E69F00", "impala": "#009E73", "dqn": "#CC79A7",
           "ddpg": "#D55E00", "td3": "#56B4E9"}
"""One colour per algorithm in every figure (Okabe-Ito, colour-blind safe); every algorithm of
the catalogue has one (tests/eval/test_layout.py)."""
EXTRA = ("#000000", "#999999", "#F0E442")
"""Colours of anything else drawn beside the algorithms (a reference policy)."""
ENV_PALETTE = ("#0072B2", "#E69F00", "#009E73", "#CC79A7", "#D55E00", "#56B4E9", "#F0E442")
"""Environment colours (Okabe-Ito), in :data:`ENVS` order."""


def algo_order(names) -> list[str]:
    """``names`` in the paper's algorithm order, anything else after it, sorted."""
    names = set(names)
    return [a for a in ALGO_ORDER if a in names] + sorted(names - set(ALGO_ORDER))


def algo_label(algo: str) -> str:
    """An algorithm's name as the study tables, their figures and the README write it: PPO, DQN
    (the catalogue's names are lower case: ppo, dqn); a name outside the catalogue the same way."""
    return algo.upper()


def colour(algo: str) -> str:
    """The algorithm's colour; a name outside the catalogue gets a fixed one of :data:`EXTRA`."""
    if algo in COLOURS:
        return COLOURS[algo]
    return EXTRA[sum(map(ord, algo)) % len(EXTRA)]


def env_colour(env: str) -> str:
    """The environment's colour: its place in :data:`ENVS`; black for a scenario YAML of one's own."""
    if env in ENVS:
        return ENV_PALETTE[ENVS.index(env) % len(ENV_PALETTE)]
    return "#000000"


def env_title(env: str) -> str:
    """The environment's title from its scenario YAML (Straight, ...), else its name."""
    try:
        from cosim.scenario import load_scenario

        return load_scenario(env).title or env
    except Exception:  # noqa: BLE001 - a report must not fail on a title
        return env
