"""The one root of every error cosim raises on purpose: :class:`CosimError`.

Why it lives here: the command line catches one class, and errors come from
both ``cosim`` (scenarios, actions, SUMO) and ``agents`` (checkpoints, worker
processes), with ``eval`` (training runs, the test protocol) on top of both.
``agents`` must never import ``cosim`` (it sees only Gymnasium spaces and
numpy arrays), so the root cannot live in ``cosim``. This module imports
nothing, and ``agents/__init__.py`` imports its submodules lazily, so
``cosim.errors`` re-exports :class:`CosimError` from here without pulling in
torch or any algorithm.

Every subclass's message names the bad input and the fix; the CLI prints it as
one line (``cosim: error: ...``) and exits non-zero.
"""


class CosimError(Exception):
    """Base class of every error cosim, agents and eval raise on purpose."""
