"""A Ray session for `cosim benchmark` and `cosim train --pbt`: local and private by default.

Ray is optional (``pip install -e '.[tune]'``) and imported only here, inside
:func:`ray_session`, so commands that run no grid never import it. A local
session listens on 127.0.0.1 only, without the dashboard and without usage
statistics; ``address`` joins an existing cluster (``ray start --head``), which
is probed first so that an address nobody answers fails in seconds, not after
Ray's own minute of retries.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import socket
from collections.abc import Iterator
from pathlib import Path

from cosim.errors import CosimError

log = logging.getLogger(__name__)

INSTALL_HINT = "Ray Tune is not installed; install it with: pip install -e '.[tune]'  (or --no-ray)"

# set before Ray starts, inherited by its processes (docs/guide.md#benchmark-on-ray)
RAY_ENV = {
    "RAY_USAGE_STATS_ENABLED": "0",
    "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0",
    "RAY_AIR_NEW_OUTPUT": "0",
    "RAY_DEDUP_LOGS": "0",
    # a grid trial's Tune checkpoint is a few-byte pointer kept with num_to_keep=1 (eval/scale/
    # benchmark.py), so Tune snapshots its experiment state at every trial checkpoint by design;
    # its "Experiment state snapshotting has been triggered multiple times" warning (3 lines each
    # time, 102 of the smoke benchmark's 111 console lines before issue 28) says nothing here; 0 turns it off
    "TUNE_WARN_EXCESSIVE_EXPERIMENT_CHECKPOINT_SYNC_THRESHOLD_S": "0",
}
# for the trials' processes, on a cluster too: a function trainable is reused (PBT,
# reuse_actors=True) only if its training thread ends within this time after a stop;
# Ray's 2 s default is shorter than a trial's env.close() and final plot
TRIAL_ENV = {"TUNE_FUNCTION_THREAD_TIMEOUT_S": "60"}


class RayError(CosimError, RuntimeError):
    """Ray is missing or a cluster cannot be reached; the message says what to do."""


def refuse_old_layout(tune_folder: Path) -> None:
    """Refuse to restore a Ray Tune folder written before ``eval/`` was split into subpackages
    (issue 26): its ``tuner.pkl`` names the trainables and the PBT scheduler by their old
    module paths (``eval.benchmark``, ``eval.pbt``, ``eval.pbt_scheduler``), which no longer
    import. Run folders, checkpoints and reports name no module and are not affected.

    Raises:
        RayError: naming the folder and what to do.
    """
    state = Path(tune_folder) / "tuner.pkl"
    if state.exists() and re.search(rb"\beval\.(benchmark|pbt|pbt_scheduler)\b", state.read_bytes()):
        raise RayError(f"--resume: {tune_folder} was written by a cosim from before eval/ was split into "
                       "subpackages (issue 26) and its Ray Tune state names modules that moved; finish it "
                       "with that cosim, or start again in a new folder")


def ray_available() -> bool:
    """Whether Ray Tune can be imported (without importing it)."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.find_spec("ray")  # find_spec("ray.tune") would import ray
    return spec is not None and any((Path(p) / "tune").is_dir()
                                    for p in spec.submodule_search_locations or ())


def probe_address(address: str, timeout: float = 3.0) -> None:
    """Fail fast when nothing listens at a ``HOST:PORT`` (or ``ray://HOST:PORT``) address.

    Raises:
        RayError: malformed address, or no answer within ``timeout`` seconds.
    """
    if address in ("auto", "local"):
        return
    hostport = address.split("://", 1)[-1]
    host, sep, port = hostport.rpartition(":")
    if not sep or not port.isdigit() or not host:
        raise RayError(f"--ray-address {address!r}: write HOST:PORT, e.g. 127.0.0.1:6379 "
                       "(the address `ray start --head` prints)")
    try:
        with socket.create_connection((host, int(port)), timeout=timeout):
            pass
    except OSError as exc:
        raise RayError(
            f"no Ray cluster answers at {address} ({exc.strerror or exc}); start one with "
            "`ray start --head --node-ip-address 127.0.0.1 --port 6379` or leave out --ray-address "
            "for a local one"
        ) from None


def _not_token_notice(record: logging.LogRecord) -> bool:
    return not record.getMessage().startswith("Token authentication is enabled for this Ray cluster")


@contextlib.contextmanager
def ray_session(address: str | None = None, num_cpus: int | None = None) -> Iterator[None]:
    """Start (or join) Ray for the duration of the block, and shut it down after.

    A local Ray's processes (GCS, raylet, workers) end with ``ray.shutdown()``, also
    when the block is left by Ctrl-C.

    Raises:
        RayError: Ray is not installed, or ``address`` does not answer.
    """
    if not ray_available():
        raise RayError(INSTALL_HINT)
    if address:
        probe_address(address)
    for key, value in {**RAY_ENV, **TRIAL_ENV}.items():
        os.environ.setdefault(key, value)
    import ray

    # Tune's TensorBoard logger warns at every -inf score (no episode finished yet)
    logging.getLogger("tensorboardX.x2num").setLevel(logging.ERROR)
    # Ray 2.60 announces that a new local cluster uses token authentication (its safe default):
    # one line of every run's console that asks nothing of the user; its warning that a
    # cluster runs *without* a token is kept
    logging.getLogger("ray._private.authentication.authentication_token_setup").addFilter(_not_token_notice)
    if ray.is_initialized():  # a caller's own session (a notebook): use it, leave it running
        yield
        return
    kwargs = {"include_dashboard": False, "log_to_driver": False, "configure_logging": False,
              "runtime_env": {"env_vars": TRIAL_ENV}}
    if address:
        try:
            ray.init(address=address, **kwargs)
        except (ConnectionError, RuntimeError) as exc:
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[-1][:200]
            raise RayError(
                f"could not join the Ray cluster at {address} ({first}); if the head uses token "
                "authentication, set RAY_AUTH_MODE=token here and give its token in RAY_AUTH_TOKEN "
                "or ~/.ray/auth_token (for an explicit address Ray 2.60 sends the token only in that mode)"
            ) from None
    else:
        ray.init(num_cpus=num_cpus or os.cpu_count() or 1, _node_ip_address="127.0.0.1", **kwargs)
    log.info("ray: %s", ray.cluster_resources())
    try:
        yield
    finally:
        ray.shutdown()
