"""Which checkpoint drives which AC slot in which environment of a test (``slots.csv``, the
console's table and the report's section): what eval/testing/policies.py loads, in words."""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from pathlib import Path

import pandas as pd

from eval.testing.checkpoints import run_of, slot_checkpoint, trained_env
from eval.testing.protocol import ProtocolPlan


def slot_table(per_env: Mapping[str, Mapping[str, Path]], plan: ProtocolPlan, algos: Sequence[str],
               fixed: Collection[str] = ()) -> pd.DataFrame:
    """Which checkpoint drives which slot in which environment (what :func:`~eval.testing.policies.policy_factory`
    loads): one row per environment, algorithm and slot: ``env, algorithm, slot, scenarios``
    (the test scenarios that drive the slot: Scenario 1 rotates the algorithms over every slot,
    Scenario 2 drives ac_0 alone), ``checkpoint, ac`` (the AC folder it comes from), ``how``
    (``own slot``: the run's AC trained in that slot; ``chosen AC``: the run's representative,
    eval/testing/selection.py; ``given``: ``--checkpoint``), ``run, trained_env, cross_env``."""
    algos = list(algos)[: plan.agents] if 1 in plan.scenarios else list(algos)
    slots = [f"ac_{k}" for k in range(len(algos))] if 1 in plan.scenarios else ["ac_0"]
    rows = []
    for env, ckpts in per_env.items():
        for algo in algos:
            chosen = Path(ckpts[algo])
            for slot in slots:
                path = chosen if algo in fixed else slot_checkpoint(chosen, slot)
                how = "given" if algo in fixed else "own slot" if path.parent.name == slot else "chosen AC"
                scen = [n for n in plan.scenarios if n == 1 or slot == "ac_0"]
                trained = trained_env(path)
                rows.append({"env": env, "algorithm": algo, "slot": slot,
                             "scenarios": " ".join(map(str, scen)), "checkpoint": str(path),
                             "ac": path.parent.name if path.parent.name.startswith("ac_") else "-",
                             "how": how,
                             "run": str(run_of(path) or ""),
                             "trained_env": trained or "unknown",
                             "cross_env": trained is not None and trained != Path(env).stem})
    return pd.DataFrame(rows)


def _summary_rows(table: pd.DataFrame) -> list[list[str]]:
    """The head and rows of :func:`slot_summary`: a row per algorithm and run (or file), the
    environments it drives in one cell, the AC folder driving each slot."""
    slots = list(dict.fromkeys(table["slot"]))
    grouped: dict[tuple, list[str]] = {}
    for (env, algo), g in table.groupby(["env", "algorithm"], sort=False):
        g = g.set_index("slot")
        cells = tuple("given" if g.at[s, "how"] == "given" else
                      g.at[s, "ac"] + ("*" if g.at[s, "how"] == "chosen AC" else "") for s in slots)
        first = g.iloc[0]
        key = (algo, first["run"] or first["checkpoint"], first["trained_env"], bool(g["cross_env"].any()), cells)
        grouped.setdefault(key, []).append(env)
    rows = [["tested in", "algorithm", "trained in", *slots, "run (or file)"]]
    for (algo, source, trained, cross, cells), envs in grouped.items():
        rows.append([" ".join(envs), algo, trained + (" (!)" if cross else ""), *cells, source])
    return rows


def slot_summary(table: pd.DataFrame) -> str:
    """:func:`slot_table` as one compact text table (the console's): a row per algorithm and
    run, the environments it drives in one cell, then the AC folder driving each slot (``*``:
    the run's chosen AC, where it trained no AC in that slot; ``given``: a ``--checkpoint``
    file; ``(!)``: trained in another environment than it drives)."""
    if table.empty:
        return ""
    rows = _summary_rows(table)
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]) - 1)]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(r[:-1], widths, strict=True)) + "  " + r[-1] for r in rows)


SLOTS_NOTE = ("Scenario 1 rotates the algorithms over every slot, Scenario 2 drives `ac_0` alone. "
              "A slot is driven by the run's AC trained in that slot; `*`: the run trained no AC "
              "there and its chosen AC drives it; `given`: a `--checkpoint` file drives every slot; "
              "\"(!)\": trained in another environment than the one tested (`--allow-cross-env`).")


def slots_markdown(table: pd.DataFrame) -> str:
    """:func:`slot_table` for the report page: a section with the compact table (as Markdown)."""
    if table.empty:
        return ""
    rows = _summary_rows(table)
    lines = ["\n## Checkpoints per environment and slot\n",
             f"Which checkpoint drives which AC slot in each tested environment (`slots.csv`). {SLOTS_NOTE}\n",
             "| " + " | ".join(rows[0]) + " |", "|" + "---|" * len(rows[0])]
    lines += ["| " + " | ".join(r[:-1]) + f" | `{r[-1]}` |" for r in rows[1:]]
    return "\n".join(lines) + "\n"

