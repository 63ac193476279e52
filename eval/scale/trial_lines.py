"""The Tune callback behind `cosim benchmark`'s line per trial (imports Ray: only
:func:`eval.scale.benchmark.run_ray` imports this module, inside its Ray session).

Tune pickles a grid's callbacks into ``tuner.pkl`` and a restored grid (``--resume``)
calls the unpickled ones, never those of the command that restores it. So the callback
keeps no count: at each trial's end it asks ``count`` (the benchmark's finished cells,
read from its folder: ``eval.scale.benchmark.finished_count``), which is right in the grid
that started and in every grid restored after it. It is a module-level class and its
functions are module-level, so the pickle names them and a restore runs today's code. It
imports nothing of the project (the benchmark hands it its functions: no import cycle).
Before 2026-11-26 it was a class local to a function, pickled by value with its count: a
restored grid said ``[1/30]`` for its third finished trial.

The folder's count alone counts a trial twice when two end close together (the second's
checkpoint is on disk before the first's line: ``[2/30]`` twice, no ``[1/30]``). So the count
read at :meth:`TrialLines.setup` (each time a grid starts or is restored) is the base, and each
line adds the trials this process has seen end since: each trial is counted once.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from ray import tune


class TrialLines(tune.Callback):
    """Say ``[k/total] trained <cell> (<seconds> s)`` (or FAILED) in the driver as each trial
    ends: k the trials of the folder's plan finished by then, the seconds since the trial
    started in this process (a restored trial: since its restart)."""

    def __init__(self, say: Callable[[str], None], count: Callable[[], tuple[int, int]],
                 name: Callable[[dict], str]):
        """``say``: prints a line; ``count``: (finished, all) trials now; ``name``: a trial's
        cell name from its config's ``cell``."""
        self.say, self.count, self.name, self.start = say, count, name, {}
        self.base: int | None = None  # trials finished when this grid (re)started
        self.ended: set[str] = set()  # trials seen finishing since

    def __getstate__(self) -> dict:
        # what a restore must not inherit: the count is read again at its setup
        return {**self.__dict__, "base": None, "ended": set()}

    def __setstate__(self, state: dict) -> None:
        # a grid started between commits 4d850cc and ea5b0b4 pickled this class with ``out``
        # and ``say`` only: its restore says each line without the count (never fails the grid)
        self.__dict__.update({"count": None, "name": None, "start": {}, "base": None,
                              "ended": set(), **state})

    def setup(self, **info):
        if self.count:
            self.base = self.count()[0]

    def on_trial_start(self, iteration, trials, trial, **info):
        self.start[trial.trial_id] = time.monotonic()

    def _line(self, trial, what: str) -> None:
        took = time.monotonic() - self.start.get(trial.trial_id, time.monotonic())
        counted = ""
        if self.count:
            finished, total = self.count()
            if what == "trained":
                self.ended.add(trial.trial_id)
            # without a setup (called by Tune before any trial) the folder's count is all we have
            done = finished if self.base is None else min(self.base + len(self.ended), total)
            counted = f"[{done}/{total}] "
        name = self.name(trial.config["cell"]) if self.name else str(trial)
        self.say(f"{counted}{what} {name} ({took:.0f} s)")

    def on_trial_complete(self, iteration, trials, trial, **info):
        self._line(trial, "trained")

    def on_trial_error(self, iteration, trials, trial, **info):
        self._line(trial, "FAILED")
