"""Environments created and closed in one process keep no memory (issue 10, item 4).

Before the fix each mirror kept ~0.75 MB (the Python lists pybullet's
``createVisualShape(vertices=...)`` never releases): 40 environments grew RSS by
~30 MB. The bound here is loose enough for allocator noise on a busy machine and
still fails with that leak; ``bench/env_memory.py`` measures 200 (docs/benchmarks.md#memory-of-environments-created-and-closed).
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cosim.mirror import mesh_file

BENCH = Path(__file__).resolve().parents[2] / "bench" / "env_memory.py"
ENVS = 40
OLD_LEAK_MB = 0.75  # per environment, measured before the fix
MAX_GROWTH_MB = 10.0  # the old leak gives ~30 MB here


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="RSS is read from Linux /proc")
def test_forty_environments_created_and_closed_keep_no_memory():
    assert OLD_LEAK_MB * ENVS > 2 * MAX_GROWTH_MB  # the bound would catch the old leak
    out = subprocess.run(
        [sys.executable, str(BENCH), "--envs", str(ENVS), "--warmup", "3", "--json"],
        capture_output=True, text=True, timeout=300, check=True,
    )
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["envs"] == ENVS
    assert r["growth_mb"] < MAX_GROWTH_MB, r
    assert r["median_per_env_mb"] < OLD_LEAK_MB / 3, r


def test_mesh_files_are_named_by_their_content():
    verts = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    tris = np.array([[0, 1, 2]])
    normals = np.tile([0.0, 0.0, 1.0], (3, 1))
    first = mesh_file(verts, tris, normals)
    assert mesh_file(verts.copy(), tris, normals) == first  # same mesh: pybullet's cache hits
    moved = mesh_file(verts + 1.0, tris, normals)
    assert moved != first and moved.exists()
    assert first.read_text().startswith("v 0.0000 0.0000 0.0000")
