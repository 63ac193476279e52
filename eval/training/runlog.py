"""A run's record while it trains: episodes.csv, TensorBoard scalars and checkpoints.

The CSV columns (:data:`EPISODE_FIELDS`) are derived from the reward-term and event
catalogues (``cosim.events.REWARD_TERMS``, ``cosim.env.EPISODE_EVENTS``), so a new
term or event gets its column without an edit here. The run folder's layout and
the two-phase checkpoint commit are described in eval/training/runfolder.py.
"""

from __future__ import annotations

import csv
import json
import logging
import os
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path

import numpy as np

from agents.errors import AgentError
from cosim.env import EPISODE_EVENTS
from cosim.errors import CosimError
from cosim.events import REWARD_TERMS
from eval.training.config import TrainConfig, TrainError
from eval.training.runfolder import atomic_write, pending_name, write_error

log = logging.getLogger(__name__)


def episode_fields(reward_terms=REWARD_TERMS, events=EPISODE_EVENTS) -> list[str]:
    """episodes.csv's columns: a reward-term sum ``r_<term>`` per reward term and a count
    ``n_<event>`` per episode event, between the fixed bookkeeping columns."""
    return ["agent", "episode", "env_step", "return", "length", *(f"r_{t}" for t in reward_terms),
            *(f"n_{e}" for e in events), "mean_speed_kmh", "DISTANCE", "distance_to_goal",
            "goal_reached", "wall_time_s"]


EPISODE_FIELDS = episode_fields()


class RunLog:
    """The run's CSV, TensorBoard writer and checkpoint bookkeeping."""

    def __init__(self, run: Path, cfg: TrainConfig, resume_state: dict | None):
        from torch.utils.tensorboard import SummaryWriter

        self.run, self.cfg = Path(run), cfg
        self.csv_path = self.run / "episodes.csv"
        state = resume_state or {}
        self.env_steps = int(state.get("env_steps", 0))
        self.episodes = dict(state.get("episodes", {}))
        self.best = dict(state.get("best", {}))
        self.best_step = dict(state.get("best_step", {}))
        self.validation = list(state.get("validation", []))
        """Every checkpoint's validation scores: [{"env_step", "scores": {ac: score}}]."""
        self.validator = None
        if cfg.validation_episodes > 0:
            from eval.training.validation import Validator

            self.validator = Validator(cfg)
        self.rows = int(state.get("csv_rows", 0))
        self.elapsed0 = float(state.get("elapsed_s", 0.0))
        self.start = time.monotonic()
        self.recent: dict[str, deque] = {f"ac_{k}": deque(maxlen=20) for k in range(cfg.agents)}
        self._truncate_csv(self.rows)
        self._file = open(self.csv_path, "a", newline="")  # noqa: SIM115 - closed in close()
        self._csv = csv.DictWriter(self._file, fieldnames=EPISODE_FIELDS, extrasaction="ignore")
        if self.rows == 0:
            try:
                self._csv.writeheader()
                self._file.flush()
            except OSError as exc:
                self._file.close()
                raise self._write_error(exc) from exc
        for row in self._read_rows():
            self.recent[row["agent"]].append(float(row["return"]))
        # the events after the checkpoint go (they are redone); the checkpoint covers its own
        # step S (episodes that ended at S are rows it kept), and purge_step drops steps >= it
        self.tb = SummaryWriter(str(self.run / "tb"), purge_step=self.env_steps + 1 if self.env_steps else None)
        self.on_checkpoint: Callable[[Path, int, float], None] | None = None

    def _write_error(self, exc: OSError) -> TrainError:
        """A failed write to episodes.csv (a full disk), its fix naming this run."""
        return TrainError(str(write_error(self.csv_path, exc)).replace("--resume RUN", f"--resume {self.run}"))

    def _read_rows(self) -> list[dict]:
        with open(self.csv_path, newline="") as f:
            return list(csv.DictReader(f))

    def _truncate_csv(self, rows: int) -> None:
        """Keep the header and the first `rows` rows (those covered by the checkpoint).

        With no rows covered (a run stopped before its first checkpoint) the file is
        removed, header and all, and written afresh.
        """
        if not self.csv_path.exists():
            return
        if rows == 0:
            self.csv_path.unlink()
            return
        with open(self.csv_path, newline="") as f:
            lines = f.readlines()
        kept = lines[: 1 + rows] if lines else []
        if len(kept) != len(lines):
            log.info("resume: dropping %d episode rows written after the last checkpoint",
                     len(lines) - len(kept))
        atomic_write(self.csv_path, "".join(kept))

    @property
    def elapsed(self) -> float:
        return self.elapsed0 + time.monotonic() - self.start

    def episode(self, agent: str, stats: dict, env_step: int) -> None:
        k = self.episodes.get(agent, 0)
        self.episodes[agent] = k + 1
        row = {**stats, "agent": agent, "episode": k, "env_step": env_step,
               "wall_time_s": round(self.elapsed, 2)}
        try:
            self._csv.writerow(row)
            self._file.flush()
        except OSError as exc:  # a full disk: the rows after the last checkpoint are redone on resume
            raise self._write_error(exc) from exc
        self.rows += 1
        self.recent[agent].append(float(stats["return"]))
        tb = self.tb
        tb.add_scalar(f"charts/episodic_return/{agent}", stats["return"], env_step)
        tb.add_scalar(f"charts/episodic_length/{agent}", stats["length"], env_step)
        tb.add_scalar("charts/mean_recent_return", self.mean_recent(), env_step)
        length = max(stats["length"], 1)
        tb.add_scalar(f"driving/collision_fraction/{agent}",
                      (stats["n_collision_vehicle"] + stats["n_collision_pedestrian"]
                       + stats["n_collision_object"]) / length, env_step)
        tb.add_scalar(f"driving/lane_violation_fraction/{agent}", stats["n_lane_violation"] / length, env_step)
        tb.add_scalar(f"driving/DISTANCE/{agent}", stats["DISTANCE"], env_step)
        tb.add_scalar(f"driving/mean_speed_kmh/{agent}", stats["mean_speed_kmh"], env_step)

    def metrics(self, agent: str, metrics: dict[str, float], env_step: int) -> None:
        for name, value in metrics.items():
            head, _, rest = name.partition("/")
            tag = f"{head}/{rest}/{agent}" if rest else f"{head}/{agent}"
            self.tb.add_scalar(tag, value, env_step)

    def mean_recent(self) -> float:
        values = [v for d in self.recent.values() for v in d]
        return float(np.mean(values)) if values else float("nan")

    def checkpoint(self, agents: dict, env_step: int, extra_time: dict[str, float] | None = None) -> None:
        """Save latest (and best) per AC and the state that makes them resumable.

        best.pt: the checkpoint with the highest validation score (held-out episodes under the
        test's rules, scored by ``select_by``: the mean driving score, ties to the later checkpoint,
        or the mean return; eval/training/validation.py; docs/task.md, "Checkpoint selection"), or with
        ``validation_episodes`` 0 the highest mean return of the AC's last 20 training
        episodes. Two phases (module docstring): pending files, then state.json, then renames.
        """
        best, best_step = dict(self.best), dict(self.best_step)
        validation = list(self.validation)
        scores = None
        if self.validator is not None:
            t0 = time.monotonic()
            both = self.validator.both(agents)  # the driving score and the return of one set of episodes
            scores = both[self.cfg.select_by]

            def rounded(values):
                return {a: round(v, 4) if np.isfinite(v) else None for a, v in values.items()}
            validation.append({"env_step": env_step, "scores": rounded(scores), "ds": rounded(both["ds"]),
                               "return": rounded(both["return"]), "seconds": round(time.monotonic() - t0, 2)})
        staged = []
        for agent_id in agents:
            folder = self.run / "checkpoints" / agent_id
            folder.mkdir(parents=True, exist_ok=True)
            names = ["latest.pt"]
            recent = self.recent[agent_id]
            score = (scores[agent_id] if scores is not None
                     else float(np.mean(recent)) if len(recent) >= 3 else np.nan)
            previous = best.get(agent_id, -np.inf)
            # the driving score is bounded and often ties (0 or 1 on every episode): the later wins
            ties_later = scores is not None and self.cfg.select_by == "ds"
            if score > previous or (ties_later and score == previous):
                best[agent_id], best_step[agent_id] = score, env_step
                names.append("best.pt")
            elif not (folder / "best.pt").exists():
                names.append("best.pt")
                best_step[agent_id] = env_step
            for name in names:
                pending = folder / pending_name(name, env_step)
                staged.append((pending, folder / name))
        state = {"env_steps": env_step, "episodes": self.episodes, "best": best,
                 "best_step": best_step, "validation": validation,
                 "csv_rows": self.rows, "elapsed_s": self.elapsed, "timing": extra_time or {}}
        try:
            for pending, final in staged:
                # latest.pt resumes training (everything); best.pt is what the test drives (the
                # policy only, a third to a fifth of the size, agents/checkpoint.py; float16 in
                # the smoke preset, TrainConfig.policy_dtype)
                policy = final.name == "best.pt"
                agents[final.parent.name].save(pending, policy_only=policy,  # a temp name, renamed
                                               policy_dtype=self.cfg.policy_dtype if policy else "float32")
            atomic_write(self.run / "state.json", json.dumps(state, indent=2))  # the commit point
        except (OSError, CosimError, AgentError) as exc:  # a full disk: this checkpoint is not committed
            for pending, _ in staged:
                pending.unlink(missing_ok=True)
            reason = " ".join(str(exc).split()).replace("--resume RUN", f"--resume {self.run}")
            kept = (f"the run keeps its checkpoint at step {self.env_steps}" if self.env_steps
                    else "the run has no checkpoint yet (a resume restarts it)")
            raise TrainError(f"checkpoint at step {env_step} not written, {kept}: {reason}") from exc
        for pending, final in staged:
            os.replace(pending, final)
        self.env_steps, self.best, self.best_step, self.validation = env_step, best, best_step, validation
        atomic_write(self.run / "selection.json", json.dumps(self.selection_record(), indent=2))
        for name, value in (extra_time or {}).items():
            self.tb.add_scalar(name, value, env_step)
        self.tb.flush()
        if self.on_checkpoint is not None:
            self.on_checkpoint(self.run, env_step, self.mean_recent())

    def selection_record(self) -> dict:
        """selection.json: how each AC's best.pt was chosen, with the scores behind it."""
        if self.validator is not None:
            from eval.training.validation import rule as rule_text

            rule = {"basis": "validation", "select_by": self.cfg.select_by,
                    "rule": rule_text(self.cfg.select_by), "seeds": self.validator.seeds,
                    "episodes": self.cfg.validation_episodes, "steps": self.cfg.validation_steps,
                    "collisions": "continue (the test's rule)"}
        else:
            rule = {"basis": "training return", "rule": "per AC, the checkpoint with the highest "
                    "mean return of its last 20 training episodes (--validation-episodes 0)"}
        best = {a: {"score": round(float(v), 4), "env_step": self.best_step.get(a)}
                for a, v in self.best.items() if np.isfinite(v)}
        representative = max(best, key=lambda a: (best[a]["score"], -int(a.rsplit("_", 1)[1])), default=None)
        return {**rule, "best": best, "representative": representative, "history": self.validation}

    def close(self) -> None:
        """Close the CSV, TensorBoard and the validator; a failed flush (a full disk, whose
        error is already on its way) is logged, not raised over it, and the rest still close."""
        for what, close in (("episodes.csv", self._file.close), ("TensorBoard", self.tb.close)):
            try:
                close()
            except OSError as exc:
                log.warning("closing %s of %s: %s", what, self.run, exc)
        if self.validator is not None:
            self.validator.close()
