"""Run `cosim train ...` and send this process a signal at an exact moment of a checkpoint.

    python tests/eval/_interrupt.py MOMENT CHECKPOINT SIGNAL -- train --algo ppo ...

MOMENT is where, in the CHECKPOINT-th checkpoint of this process (1-based), the
signal (KILL or INT) arrives:

    enter      before anything of it is written
    saving     halfway through writing an AC's checkpoint file (half the bytes on disk)
    pending    every AC's pending file written, state.json not yet replaced
    committed  state.json replaced, the pending files not yet renamed

The training code is not changed: the hooks wrap the functions it calls.
"""

import io
import os
import signal
import sys

import torch

import agents.checkpoint
import eval.training.runlog
from eval.cli import main

calls = {"checkpoint": 0, "fired": 0}
moment, nth, sig = "", 0, signal.SIGKILL


def fire() -> None:
    calls["fired"] += 1
    os.kill(os.getpid(), sig)


real_checkpoint = eval.training.runlog.RunLog.checkpoint


def checkpoint(self, *args, **kwargs):
    calls["checkpoint"] += 1
    if moment == "enter" and calls["checkpoint"] == nth:
        fire()
    return real_checkpoint(self, *args, **kwargs)


real_write = eval.training.runlog.atomic_write  # how RunLog.checkpoint writes state.json


def atomic_write(path, text):
    hit = path.name == "state.json" and calls["checkpoint"] == nth
    if hit and moment == "pending":
        fire()
    real_write(path, text)
    if hit and moment == "committed":
        fire()


real_save_file = agents.checkpoint._write  # how a checkpoint file is written (temp name, renamed)


def save_file(payload, path):
    if moment == "saving" and calls["checkpoint"] == nth:
        buffer = io.BytesIO()
        torch.save(payload, buffer)  # leave the temp file half written, as a kill mid-write would
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_bytes(buffer.getvalue()[: len(buffer.getvalue()) // 2])
        fire()
    return real_save_file(payload, path)


if __name__ == "__main__":  # worker processes (spawn) import this module again
    moment, nth, sig = sys.argv[1], int(sys.argv[2]), getattr(signal, f"SIG{sys.argv[3]}")
    eval.training.runlog.RunLog.checkpoint = checkpoint
    eval.training.runlog.atomic_write = atomic_write
    agents.checkpoint._write = save_file
    code = main(sys.argv[sys.argv.index("--") + 1:])
    if not calls["fired"]:  # say why, for the test's failure message
        print(f"_interrupt.py: {sys.argv[3]} at {moment!r} of checkpoint {nth} never fired: this "
              f"process made {calls['checkpoint']} checkpoint(s) and exited {code}", file=sys.stderr)
    sys.exit(code)
