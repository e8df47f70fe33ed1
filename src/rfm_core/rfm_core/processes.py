"""Child processes that die with their parent, however it dies; math libraries that stay on
one thread.

``rfm run`` starts its nodes and the bag player as processes of their own, and ``rfm eval``
starts ``rfm run``: killed with SIGKILL (the OOM killer, ``docker kill``, a closed terminal)
a parent cannot stop them, and they would go on autosaving and join the next run's graph.
:func:`die_with_parent`, given to :class:`subprocess.Popen` as ``preexec_fn``, asks Linux to
send the child SIGTERM when its parent ends (``prctl(PR_SET_PDEATHSIG)``); elsewhere it does
nothing.

A node's matrices are small (a few dozen boxes, 256-wide tokens): numpy's OpenBLAS would run
them on every core, and its idle threads spin, taking CPU from the other nodes (on the demo
the detector used 2.4 times the CPU). :func:`limit_blas_threads` keeps it to one thread.
"""
from __future__ import annotations

import ctypes
import os
import signal

__all__ = ['die_with_parent', 'limit_blas_threads']

_BLAS_SETTERS = ('scipy_openblas_set_num_threads64_', 'scipy_openblas_set_num_threads',
                 'openblas_set_num_threads64_', 'openblas_set_num_threads')

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


def limit_blas_threads(threads: int = 1) -> int:
    """Keep every OpenBLAS this process has loaded (numpy's, scipy's) to ``threads`` threads,
    unless the user chose (``OPENBLAS_NUM_THREADS`` or ``OMP_NUM_THREADS`` set). Returns how
    many libraries it set (0 off Linux or without OpenBLAS)."""
    if 'OPENBLAS_NUM_THREADS' in os.environ or 'OMP_NUM_THREADS' in os.environ:
        return 0
    import numpy  # noqa: F401, PLC0415 - loads numpy's OpenBLAS
    import scipy.linalg  # noqa: F401, PLC0415 - and scipy's
    try:
        with open('/proc/self/maps') as f:
            paths = {line.split()[-1] for line in f if 'openblas' in line.lower() and '/' in line}
    except OSError:
        return 0
    done = 0
    for path in sorted(paths):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        setter = next((getattr(lib, name) for name in _BLAS_SETTERS if hasattr(lib, name)), None)
        if setter is not None:
            setter(ctypes.c_int(threads))
            done += 1
    return done
