"""studies/bc_warmstart.py (issue 25's behaviour-cloning diagnostic): discounted returns, and
its smoke version end to end: demonstrations labelled by the discrete autopilot, a PPO clone
that cosim train can warm-start from, its test and summary, a rerun that redoes nothing."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = ROOT / "studies" / "bc_warmstart.py"


@pytest.fixture(scope="module")
def bc(load_study):
    return load_study("bc_warmstart")


def test_discounted_returns(bc):
    np.testing.assert_allclose(bc.discounted([1.0, 0.0, 2.0], 0.5), [1.5, 1.0, 2.0])
    assert bc.discounted([], 0.9).shape == (0,)


def test_smoke_end_to_end_and_rerun(tmp_path):
    import agents
    from eval.training.config import make_config
    from eval.training.trainer import _load_or_build, make_env

    cmd = [sys.executable, str(SCRIPT), "--smoke", "--out", str(tmp_path)]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    with np.load(tmp_path / "demos" / "env_4.npz") as f:
        demos = {k: f[k] for k in f.files}
    n = len(demos["actions"])
    assert n == 2 * 30  # the smoke's 2 ACs, 60 steps held 2 at a time, no goal on the way
    assert demos["image"].shape == (n, 84, 84, 12) and demos["measurements"].shape[0] == n
    assert set(demos["actions"]) <= set(range(9)) and np.isfinite(demos["returns"]).all()
    clone = agents.load(tmp_path / "bc_ppo.pt")
    assert clone.algo == "ppo" and clone.config.action_repeat == 2
    assert (tmp_path / "test" / "env_4.parquet").exists()
    assert "| bc clone ppo |" in (tmp_path / "summary.md").read_text()
    cfg = make_config("ppo", "env_4", "smoke", agents=2, obs="nav", share_params=True,
                      hyper={"action_repeat": "2"}, init_from=tmp_path / "bc_ppo.pt")
    env = make_env(cfg)
    try:  # the clone is a warm start for the run config it was built for
        slots = _load_or_build(cfg, tmp_path, False, env.observation_space("ac_0"), env.action_space("ac_0"))
    finally:
        env.close()
    for key, tensor in clone.net.state_dict().items():
        assert np.array_equal(slots["ac_1"].net.state_dict()[key].numpy(), tensor.numpy()), key
    again = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0 and "demos env_4" not in again.stderr and "clone epoch" not in again.stderr
