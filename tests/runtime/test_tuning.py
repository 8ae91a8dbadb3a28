"""Process-wide settings of runtime.tuning, each checked in a fresh interpreter (they change the process)."""

import json
import os
import subprocess
import sys

import pytest

PROBE = """
import gc, json, os
from runtime.tuning import freeze_startup, one_thread_per_process
one_thread_per_process()
import scipy.linalg  # loaded after: reads the environment
from threadpoolctl import threadpool_info
freeze_startup()
print(json.dumps({"blas": [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"],
                  "env": os.environ.get("OPENBLAS_NUM_THREADS"), "frozen": gc.get_freeze_count()}))
"""


def _probe(**env: str) -> dict:
    base = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, check=True,
                         env={**base, **env})
    return json.loads(out.stdout)


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="BLAS already uses one thread on one core")
def test_one_blas_thread_for_the_process_and_its_children():
    r = _probe()
    assert r["blas"] and all(n == 1 for n in r["blas"])  # numpy's and scipy's OpenBLAS
    assert r["env"] == "1"  # inherited by the processes it starts
    assert r["frozen"] > 1000  # start-up objects out of the collector's way


@pytest.mark.skipif((os.cpu_count() or 1) < 2, reason="needs 2 cores to see 2 threads")
def test_an_explicit_thread_count_wins():
    r = _probe(OPENBLAS_NUM_THREADS="2")
    assert r["env"] == "2" and 2 in r["blas"]
