"""Test-session set-up shared by every tier.

A test run started in the background by a non-interactive shell (``pytest ... &`` in a
script, ``nohup``, some CI runners) inherits SIGINT *ignored*, and so does every process
it starts: a Ctrl-C sent to a trainer under test would be lost and the trainer would run
on (the three signal tests of issue 24 hung or finished with exit code 0 exactly so).
Python installs its KeyboardInterrupt handler only where SIGINT is not ignored, so the
session puts it back; processes the tests start then get SIGINT's default and handle it.
"""

import signal

if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)
