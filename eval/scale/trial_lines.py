"""The Tune callback behind `cosim benchmark`'s line per trial (imports Ray: only
:func:`eval.scale.benchmark.run_ray` imports this module, inside its Ray session).

Tune pickles a grid's callbacks into ``tuner.pkl`` and a restored grid (``--resume``)
calls the unpickled ones, never those of the command that restores it. So the callback
keeps no count: at each trial's end it counts the finished trials in the benchmark folder
(eval/scale/gridstatus.py), which is right in the grid that started and in every grid
restored after it. It is a module-level class, so the pickle names it and a restore runs
today's code. (Before 2026-11-26 it was a class local to a function, pickled by value with
its count: a restored grid said ``[1/30]`` for its third finished trial.)
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from ray import tune

from eval.scale.gridstatus import grid_status


class TrialLines(tune.Callback):
    """Say ``[k/total] trained <cell> (<seconds> s)`` (or FAILED) in the driver as each trial
    ends: k the trials of the folder's plan finished by then, the seconds since the trial
    started in this process (a restored trial: since its restart)."""

    def __init__(self, out: Path, say: Callable[[str], None]):
        self.out, self.say, self.start = Path(out), say, {}

    def on_trial_start(self, iteration, trials, trial, **info):
        self.start[trial.trial_id] = time.monotonic()

    def _line(self, trial, what: str) -> None:
        from eval.scale.benchmark import cell_name

        took = time.monotonic() - self.start.get(trial.trial_id, time.monotonic())
        table = grid_status(self.out)
        done = int((table.state == "finished").sum())
        self.say(f"[{done}/{len(table)}] {what} {cell_name(trial.config['cell'])} ({took:.0f} s)")

    def on_trial_complete(self, iteration, trials, trial, **info):
        self._line(trial, "trained")

    def on_trial_error(self, iteration, trials, trial, **info):
        self._line(trial, "FAILED")
