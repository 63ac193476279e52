"""The driving task's version (re-exported as ``cosim.TASK_VERSION``; the env ids carry it)."""

TASK_VERSION = 5
"""The driving task's version, recorded in every run's manifest.json and every report's
provenance.json (``task_version``) so a results folder says which task it measured:

1. 2026-11-20 to 11-24: the paper's discrete steer fractions of a 35 degree wheel, no grip limit;
   training episodes ended at a collision; one camera frame; best.pt by training return.
2. since 2026-11-24 (issue 25; docs/task.md): the fractions of CARLA's 70 degree wheel with a
   grip limit; collisions go on and every contact step is charged, in training as in the test;
   4 stacked frames by default; best.pt by validation under the test's rules. Runs record
   the options that select variants (``--obs``, ``--frame-stack``, ``--collisions``,
   ``--share-params``) in their config.yaml.
3. since 2026-11-26: as 2, and SUMO's cars and people wait for an AC on their path through a
   junction (``SumoBridge.gate_entries``; docs/scenarios.md): background traffic no longer
   sets off into an AC that is still in the junction.
4. since 2026-12-01 (docs/task.md, "Collision rule" and "Driving score"): a contact is charged
   once per collision event (one per other actor within 5 s) and the episode goes on; a car
   ahead that an AC drives into is solid, as road objects are; SUMO's cars and people brake for
   an AC body in their path on a lane or not (``Scenario.cars_see_acs``); the test's headline
   metric is the driving score.
5. since 2026-12-02 (docs/task.md, "Collision rule", "Who is charged"): the reward charges a
   vehicle contact only to the car at fault (the one that drove into the other; Contact.fault
   ``at_fault``, ``cosim train --fault both`` for version 4's rule); the test's driving score
   still counts every event a car is in. The speed term F pays only on new ground (a step that
   leaves the AC nearer its goal than it has been), so a car bouncing off what it drove into no
   longer earns F on the metre it was put back.

The env ids carry the version (``cosim_v5``, ``cosim/FourWay-v5``), as Gymnasium and PettingZoo
version an environment whose behaviour changed.
"""
