"""A second SUMO simulation of a process, run by libsumo in a child process of its own.

libsumo holds one simulation per process. Before issue 57 a second one (a training run's
validation environment beside its training environment, two environments alive at once) ran
SUMO through TraCI, whose server listens on a TCP port of every interface (``0.0.0.0``, SUMO
has no option to bind it to 127.0.0.1) and has no authentication. :class:`SumoProcess` opens
no port: it starts ``python sumo_process.py FD PID``, whose libsumo runs the simulation, and
sends it every call (``ls.vehicle.setSpeed("c1", 0.0)``: the dotted name, the arguments)
over a private socket pair, pickled, one answer per call, as TraCI would over TCP. So the
bridge (``cosim/sumo_bridge.py``) drives it exactly as it drives libsumo in-process.

A failed libsumo call raises :class:`SumoCallError` with libsumo's message, as does a child
that ended (its exit code). The child ends with its parent: the socket's end of file, and a
watch on its parent's pid (a parent killed with SIGKILL leaves no simulation running). This
module imports nothing of cosim, so the child starts without importing the package.
"""

from __future__ import annotations

import functools
import os
import pickle
import signal
import socket
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection

__all__ = ["SumoCallError", "SumoProcess"]

FUNCTIONS = frozenset({"start", "load", "close", "simulationStep", "isLoaded", "getVersion"})
"""libsumo's module-level functions; every other name is a domain (``vehicle``, ``simulation``)."""
PARENT_POLL_S = 0.5
"""How often the child checks that its parent still lives (its pid is still the parent's)."""
_BOOT = "import runpy, sys; runpy.run_path(sys.argv[1], run_name='__main__')"


class SumoCallError(RuntimeError):
    """A libsumo call in the SUMO process failed (its message), or the process ended."""


class _Domain:
    """``proxy.vehicle``: its attributes are the calls ``vehicle.<name>`` in the child."""

    def __init__(self, call, name: str):
        self._call, self._name = call, name

    def __getattr__(self, attr: str):
        if attr.startswith("_"):
            raise AttributeError(attr)
        method = functools.partial(self._call, f"{self._name}.{attr}")
        setattr(self, attr, method)  # found once per name
        return method


class SumoProcess:
    """libsumo's API (``start``, ``load``, ``simulationStep``, ``close`` and the domains) for a
    simulation in a child process; ``close()`` closes SUMO and ends the child (idempotent)."""

    def __init__(self):
        mine, theirs = socket.socketpair()
        try:
            self._proc = subprocess.Popen(
                # -P: no current folder on sys.path (a sumo.py there is not imported)
                [sys.executable, "-P", "-c", _BOOT, __file__, str(theirs.fileno()), str(os.getpid())],
                pass_fds=(theirs.fileno(),), stdin=subprocess.DEVNULL, close_fds=True)
        except BaseException:
            mine.close()
            raise
        finally:
            theirs.close()
        self._conn: Connection | None = Connection(mine.detach())
        self._lock = threading.Lock()  # one call at a time: the answers come back in order
        self._why = "the SUMO process is closed"  # what a call after the end says
        self._domains: dict[str, _Domain] = {}

    @property
    def pid(self) -> int:
        return self._proc.pid

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        if name in FUNCTIONS:
            return functools.partial(self._call, name)
        if name not in self._domains:
            self._domains[name] = _Domain(self._call, name)
        return self._domains[name]

    def _call(self, name: str, *args, **kwargs):
        with self._lock:
            if self._conn is None:
                raise SumoCallError(f"{name}: {self._why}")
            try:
                self._conn.send((name, args, kwargs))
                ok, value = self._conn.recv()
            except (EOFError, OSError) as exc:
                self._end()
                self._why = f"the SUMO process ended (exit code {self._proc.returncode})"
                raise SumoCallError(f"{name}: {self._why}") from exc
            except BaseException:  # Ctrl-C amid a call: its answer would answer the next one
                self._end(wait_s=1.0)
                raise
        if not ok:
            raise SumoCallError(value)
        return value

    def close(self) -> None:
        """Close the simulation and end the child; safe to call twice."""
        if self._conn is None:
            return
        try:
            self._call("close")
        except SumoCallError:  # nothing was started, or the child is already gone
            pass
        finally:
            with self._lock:
                self._end()

    def _end(self, wait_s: float = 5.0) -> None:
        conn, self._conn = self._conn, None
        if conn is not None:
            conn.close()  # the child's end of file: it closes SUMO and exits
        try:
            self._proc.wait(timeout=wait_s)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()

    def __del__(self):
        try:
            if getattr(self, "_conn", None) is not None:
                self._end(wait_s=1.0)
        except Exception:  # interpreter shutdown
            pass


def _watch_parent(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(PARENT_POLL_S)
    os._exit(1)  # the parent died (we were re-parented): end now, with SUMO


def _serve(fd: int, parent: int) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle: it closes us
    conn = Connection(fd)
    threading.Thread(target=_watch_parent, args=(parent,), daemon=True).start()
    import sumo

    os.environ.setdefault("SUMO_HOME", sumo.SUMO_HOME)
    import libsumo

    while True:
        try:
            name, args, kwargs = conn.recv()
        except (EOFError, OSError):
            break
        try:
            target = libsumo
            for part in name.split("."):
                target = getattr(target, part)
            reply = (True, target(*args, **kwargs))
        except libsumo.TraCIException as exc:
            reply = (False, str(exc))
        except Exception as exc:  # a bad name or argument: the caller's bug, named
            reply = (False, f"{name}: {type(exc).__name__}: {exc}")
        try:
            conn.send(reply)
        except (pickle.PicklingError, TypeError, AttributeError) as exc:
            conn.send((False, f"{name}: its result cannot be sent back ({exc})"))
        except OSError:
            break
    try:
        libsumo.close()
    except Exception:  # nothing was running
        pass


if __name__ == "__main__":
    _serve(int(sys.argv[2]), int(sys.argv[3]))
