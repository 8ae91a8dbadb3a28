"""Lazy compiled kernels (glassmap.jit): numba is imported by the first call, not by importing a module."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from glassmap import registration_jit
from glassmap.jit import LazyKernel
from glassmap.registration import decay_exponents


def test_importing_the_mapper_or_the_map_worker_does_not_import_numba():
    code = ("import sys, glassmap.mapping, glassmap.glass_features, glassmap.sim.laser, runtime.map_worker; "
            "print('numba' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_a_call_compiles_the_module_kernels_and_gives_the_python_result():
    assert isinstance(decay_exponents, LazyKernel)  # importers keep the lazy object and call through it
    dist, sigma = np.array([0.0, 0.05, 0.1]), np.array([0.02, 0.04])
    np.testing.assert_array_equal(decay_exponents(dist, sigma), decay_exponents.py_func(dist, sigma))
    import numba

    # the module's globals are numba dispatchers now, so kernels calling kernels are typed by numba
    for name in ("nearest_cells", "window_observations", "decay_exponents", "decayed"):
        assert isinstance(getattr(registration_jit, name), numba.core.registry.CPUDispatcher), name
