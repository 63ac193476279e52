"""Synchronous Population Based Training that `Tuner.restore` can continue (Ray 2.60).

Ray Tune saves the searcher's state with the experiment but not the scheduler's
(ray-project/ray#30838): `Tuner.restore` brings back the scheduler pickled in
``tuner.pkl`` when the run started, i.e. with no trial state (every trial at
time 0) and its first synchronisation barrier at the first interval. A synchronous
PBT interrupted by Ctrl-C also stops with its trials one interval apart: the
trials that reached the barrier wait there (PAUSED, checkpoint at the barrier),
the others are mid-interval (their last checkpoint one interval earlier). On
restore every trial restarts at once; after the first barrier the stock scheduler
sets its next barrier to ``max(next + interval, latest time)``, which equals the
time of every trial once the laggard exploited the leader, and
``choose_trial_to_run`` (which starts only trials *before* the barrier) never
starts one again: "No trial is running" forever (the same stall ray-project/ray#48616
proposed to fix upstream; not in 2.60).

:class:`ResumablePBT` restores what the scheduler forgot from each restored trial's
latest checkpoint (its time, score and result), holds the trials that are ahead
as PAUSED until the laggards reach them (so the next barrier compares trials at the
same step, as an uninterrupted run does), and never lets the next barrier fall on
or before the slowest live trial.

It also makes every exploit explore: Ray's explore step can hand a clone its donor's
hyperparameters unchanged (a list value at an end shifted outward stays, a resample can draw
the same value; with two two-valued hyperparameters about a fifth of the draws, tests/eval/test_pbt_scheduler.py),
which is a copy, not PBT's explore. :meth:`ResumablePBT._get_new_config` draws again until at least one
mutated hyperparameter differs from the donor's.
"""

from __future__ import annotations

from ray.tune.experiment import Trial
from ray.tune.schedulers import PopulationBasedTraining


class ResumablePBT(PopulationBasedTraining):
    """``PopulationBasedTraining(synch=True)`` whose state is rebuilt on `Tuner.restore`."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._restored = False

    def on_trial_add(self, tune_controller, trial: Trial):
        super().on_trial_add(tune_controller, trial)
        restored = trial.latest_checkpoint_result
        metrics = restored.metrics if restored is not None and restored.checkpoint else {}
        if trial.status == Trial.PENDING and self._time_attr in metrics and self._metric in metrics:
            # a trial coming back from an experiment checkpoint (a new trial has none)
            state = self._trial_state[trial]
            state.last_train_time = state.last_perturbation_time = metrics[self._time_attr]
            state.last_score = self._metric_op * metrics[self._metric]
            state.last_result = dict(metrics)
            # the controller files the trial under this status right after this call
            # (TuneController.add_trial); choose_trial_to_run starts a PAUSED trial
            # only while it is behind the next barrier
            trial.set_status(Trial.PAUSED)
            self._restored = True
        if self._restored and self._synch:
            self._next_perturbation_sync = max(self._slowest() + self._perturbation_interval,
                                               self._burn_in_period)

    def on_trial_result(self, tune_controller, trial: Trial, result: dict) -> str:
        decision = super().on_trial_result(tune_controller, trial, result)
        if self._synch and self._next_perturbation_sync <= self._slowest():
            # every live trial at or past the barrier: none could ever be started again
            self._next_perturbation_sync = self._slowest() + self._perturbation_interval
        return decision

    def _get_new_config(self, trial: Trial, trial_to_clone: Trial):
        donor = trial_to_clone.config
        for _ in range(100):  # each draw changes something with probability >= 1/2 per list
            new_config, operations = super()._get_new_config(trial, trial_to_clone)
            if any(new_config[k] != donor[k] for k in self._hyperparam_mutations):
                break
        return new_config, operations

    def _slowest(self) -> float:
        times = [s.last_train_time for t, s in self._trial_state.items() if not t.is_finished()]
        return min(times) if times else 0
