"""Process-level set-up every node shares: numpy's and scipy's BLAS on one thread."""
import json
import os
import subprocess
import sys

CODE = ('import ctypes, json\n'
        'from rfm_core.processes import limit_blas_threads\n'
        'n = limit_blas_threads()\n'
        "libs = {l.split()[-1] for l in open('/proc/self/maps') if 'openblas' in l.lower() and '/' in l}\n"
        'counts = []\n'
        'for path in libs:\n'
        '    lib = ctypes.CDLL(path)\n'
        "    get = [getattr(lib, g) for g in ('scipy_openblas_get_num_threads64_', 'scipy_openblas_get_num_threads',\n"
        "                                      'openblas_get_num_threads64_', 'openblas_get_num_threads') if hasattr(lib, g)]\n"
        '    counts += [get[0]()] if get else []\n'
        'print(json.dumps([n, counts]))\n')


def _run(**env):
    clean = {k: v for k, v in os.environ.items() if k not in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS')}
    out = subprocess.run([sys.executable, '-c', CODE], capture_output=True, text=True, timeout=60,
                         env=clean | env, check=True).stdout
    return json.loads(out)


def test_blas_runs_on_one_thread_unless_the_user_chose():
    n, counts = _run()
    assert n >= 1 and counts and all(c == 1 for c in counts), (n, counts)
    n, counts = _run(OPENBLAS_NUM_THREADS='2')
    assert n == 0 and all(c == min(2, os.cpu_count()) for c in counts), (n, counts)
