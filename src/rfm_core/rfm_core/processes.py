"""Child processes that die with their parent, however it dies.

``rfm run`` starts its nodes and the bag player as processes of their own, and ``rfm eval``
starts ``rfm run``: killed with SIGKILL (the OOM killer, ``docker kill``, a closed terminal)
a parent cannot stop them, and they would go on autosaving and join the next run's graph.
:func:`die_with_parent`, given to :class:`subprocess.Popen` as ``preexec_fn``, asks Linux to
send the child SIGTERM when its parent ends (``prctl(PR_SET_PDEATHSIG)``); elsewhere it does
nothing.
"""
from __future__ import annotations

import ctypes
import os
import signal

__all__ = ['die_with_parent']

_PR_SET_PDEATHSIG = 1


def die_with_parent(parent_pid: int | None = None):
    """A ``preexec_fn`` for :class:`subprocess.Popen`: the child gets SIGTERM once the process
    that started it (``parent_pid``, default this one) ends, also if it ended before the
    child could ask. Popen from a thread that outlives the child (the signal follows the
    thread that forked)."""
    parent = os.getpid() if parent_pid is None else parent_pid

    def preexec() -> None:
        try:
            ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM))
        except (OSError, AttributeError):           # not Linux: nothing to ask for
            return
        if os.getppid() != parent:                  # the parent died before we asked
            os.kill(os.getpid(), signal.SIGTERM)
    return preexec
