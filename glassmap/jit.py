"""Compiled kernels loaded at first use: numba (with LLVM, ~110 MiB resident) is imported only by a process
that calls a kernel, not by every process that imports a module defining one (e.g. the runtime's map
worker, which imports :mod:`glassmap.mapping` but never runs a kernel).

``@njit(**options)`` marks a kernel like ``numba.njit(**options)``. At the first call of any kernel of a
module, numba is imported and every kernel of that module is compiled (or loaded from numba's on-disk
cache), and the module's globals are replaced by the compiled dispatchers, so kernels that call each other
are typed by numba as usual. Callers holding the :class:`LazyKernel` keep calling through it.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

_lock = threading.Lock()


class LazyKernel:
    """A python function to be compiled by ``numba.njit(**options)`` at the first call."""

    def __init__(self, py_func: Callable, options: dict[str, Any]) -> None:
        self.py_func = py_func
        self.options = options
        self._compiled: Callable | None = None
        self.__name__ = py_func.__name__
        self.__qualname__ = py_func.__qualname__
        self.__doc__ = py_func.__doc__
        self.__module__ = py_func.__module__

    def __call__(self, *args):
        f = self._compiled
        if f is None:
            f = self.compiled()
        return f(*args)

    def compiled(self) -> Callable:
        """The numba dispatcher (imports numba and swaps in every kernel of this module on the first call)."""
        if self._compiled is None:
            with _lock:
                if self._compiled is None:
                    import numba

                    g = self.py_func.__globals__
                    for name, v in list(g.items()):
                        if isinstance(v, LazyKernel) and v._compiled is None:
                            v._compiled = numba.njit(**v.options)(v.py_func)
                            g[name] = v._compiled
        return self._compiled


def njit(**options: Any) -> Callable[[Callable], LazyKernel]:
    """Decorator: a :class:`LazyKernel` compiled with ``numba.njit(**options)`` at first use."""

    def wrap(py_func: Callable) -> LazyKernel:
        return LazyKernel(py_func, options)

    return wrap
