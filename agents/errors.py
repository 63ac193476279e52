"""The root of every error the ``agents`` package raises on purpose: :class:`AgentError`.

``agents`` sees only Gymnasium spaces and numpy arrays and never imports ``cosim`` or
``eval``, so it has its own root rather than sharing cosim's: checkpoints
(:class:`agents.checkpoint.CheckpointError`) and worker processes
(:class:`agents.workers.WorkerError`) subclass it. This module imports nothing, and
``agents/__init__.py`` imports its submodules lazily, so catching :class:`AgentError`
does not pull in torch.

Every subclass's message names the bad input and the fix; the command line
(``eval/cli/__init__.py``) catches this root and ``cosim.errors.CosimError`` alike and prints the
message as one line (``cosim: error: ...``; exit codes: docs/reference.md#exit-codes-and-errors).
"""

__all__ = ["AgentError"]


class AgentError(Exception):
    """Base class of every error the agents package raises on purpose."""
