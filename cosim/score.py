"""The driving score: the headline test metric (docs/task.md, "Driving score").

Per AC-episode, as the CARLA Leaderboard scores a route:

    driving score DS = route completion RC x infraction penalty IP

- RC (0..1): the fraction of the route's length driven along the route's lanes: the furthest
  net progress credited by the reward's ``progress`` term (metres towards the goal, credited
  only on the road and in the route's lanes, so a shortcut or the wrong side never counts),
  over the route's length from the spawn point to the goal; 1.0 when the goal is reached.
- IP: the product of one factor per infraction event: pedestrian 0.50, vehicle 0.60, static
  object 0.65, red light 0.70. A collision event is one contact with one other actor; the same
  actor again within :data:`cosim.events.EVENT_WINDOW_S` (5 s) is the same event.
- success: the goal reached with no infraction.

A car that never moves scores 0; partial progress counts.
"""

from __future__ import annotations

INFRACTION_FACTORS = {"pedestrian": 0.50, "vehicle": 0.60, "object": 0.65, "red_light": 0.70}
"""CARLA Leaderboard's penalty per event of each kind (collision with a pedestrian, a vehicle,
a static object; crossing a red light)."""


def infraction_penalty(vehicle: int = 0, pedestrian: int = 0, obj: int = 0, red_light: int = 0) -> float:
    """The product of the factors, one per event of each kind (counts of events, >= 0)."""
    counts = {"vehicle": vehicle, "pedestrian": pedestrian, "object": obj, "red_light": red_light}
    penalty = 1.0
    for kind, n in counts.items():
        if n < 0:
            raise ValueError(f"the count of {kind} events must be >= 0, got {n}")
        penalty *= INFRACTION_FACTORS[kind] ** int(n)
    return penalty


def driving_score(route_completion: float, penalty: float) -> float:
    """RC x IP, with RC clipped to 0..1."""
    return min(max(float(route_completion), 0.0), 1.0) * float(penalty)


def episode_score(route_completion: float, goal: bool, vehicle: int = 0, pedestrian: int = 0,
                  obj: int = 0, red_light: int = 0) -> dict[str, float]:
    """One AC-episode's ``DS``, ``RC`` (1.0 at the goal, else clipped to 0..1), ``IP`` and
    ``success`` (the goal with no infraction) from its route completion and event counts."""
    rc = 1.0 if goal else min(max(float(route_completion), 0.0), 1.0)
    ip = infraction_penalty(vehicle, pedestrian, obj, red_light)
    clean = vehicle + pedestrian + obj + red_light == 0
    return {"DS": driving_score(rc, ip), "RC": rc, "IP": ip, "success": float(bool(goal) and clean)}


class RouteCompletion:
    """The running route completion of one AC-episode from the per-step credited progress.

    ``update(progress, goal_reached)`` adds one step's credited progress (metres, as
    ``Events.progress``: negative when moving away from the goal) and returns RC so far: the
    furthest net progress over the route's length, clipped to 0..1; 1.0 from the goal on.
    """

    def __init__(self, length: float):
        if not length > 0:
            raise ValueError(f"a route's length must be > 0 metres, got {length}")
        self.length = float(length)
        self.net = 0.0
        self.best = 0.0
        self.done = False

    def update(self, progress: float, goal_reached: bool = False) -> float:
        self.net += float(progress)
        self.best = max(self.best, self.net)
        self.done = self.done or bool(goal_reached)
        return self.value

    @property
    def value(self) -> float:
        return 1.0 if self.done else min(max(self.best / self.length, 0.0), 1.0)
