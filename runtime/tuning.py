"""Process-wide settings for a steady per-scan time: one BLAS thread, start-up objects kept out of the
garbage collector's way.

- The runtime's numeric work is a stream of small matrix products (1081 beams x a few dozen columns) in
  one processing thread. OpenBLAS would run each on a team of one thread per core; on a 2-core laptop that
  shares its cores with the drivers, the emulated devices and other programs, such a team spends most of
  its time waiting for its own threads (a 1081 x 19 -> 32 -> 32 -> 16 -> 2 network: ~20x slower than on
  one thread). :func:`one_blas_thread` limits every BLAS library loaded in this process to one thread;
  :data:`ONE_THREAD_ENV` does the same for libraries loaded later and for child processes (read when their
  libraries load). The ``glassmap`` program does both at start (:func:`setup_process`), and so do the
  benchmark's child processes: its parallel jobs are processes (replays, benchmark, experiment), each
  single-threaded.
- CPython's full garbage collection walks every tracked object; after the imports (numpy, scipy,
  rosbags, ...) that is ~10^5 objects and a pause of tens of milliseconds, taken by whichever thread
  allocates at that moment (often the processing thread in the middle of a scan). :func:`freeze_startup`
  moves everything alive after start-up into the permanent generation, so later collections only walk
  what the run itself creates.
- glibc's malloc gives each thread that allocates its own arena (up to 8 per core) and keeps freed memory in
  each; the runtime's threads (event loop, processing, likelihood field, recorder) each hold tens of MiB
  of freed numpy buffers that way. :func:`one_malloc_arena` makes every thread share one arena (small
  allocations still go through each thread's cache, and most of the runtime's allocation happens under
  the interpreter lock anyway).
- Memory written for the first time costs a page fault per page, and in a virtual machine whose host takes
  freed guest memory back (free page reporting) each such fault also waits for the host. The grid grows at
  the first scans (every layer copied into new, larger arrays: tens of MiB), and glibc serves buffers that
  large from fresh mappings and gives freed memory back at once, so the processing thread stalls while
  scans queue up. :func:`reserve_heap` is the usual real-time Linux recipe: large buffers from the heap
  (``M_MMAP_MAX`` 0), free() keeps memory (no ``M_TRIM_THRESHOLD``), and a reserve written once at
  start-up, so the first growths reuse pages already mapped; :func:`release_heap_reserve` undoes it.
- numba loads the compiled kernels (from its on-disk cache) through LLVM, a 170 MB shared library
  (llvmlite's), at start-up; after that the kernels run as plain machine code and LLVM's pages are not
  touched again (unless a kernel meets new argument types and is compiled). Linux kernels that map file
  pages in large folios keep ~70-100 MiB of them resident for nothing. :func:`release_compiler_pages` hands
  them back (``madvise(MADV_PAGEOUT)``); a page that is needed again is read back in on its first use.
"""

from __future__ import annotations

import ctypes
import gc
import logging
import os
import sys

_log = logging.getLogger(__name__)

ONE_THREAD_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
BACKGROUND_NICE = 5  # niceness increment of the helper processes: on a busy machine the scans come first


def background_priority() -> None:
    """Lower this process's scheduling priority by :data:`BACKGROUND_NICE` (helper processes whose work can
    wait: map exports, the pose graph); silently nothing where the system refuses."""
    try:
        os.nice(BACKGROUND_NICE)
    except OSError:
        pass


def thread_priority(nice: int) -> bool:
    """Set the calling thread's niceness (Linux: a thread's own scheduling priority; -20 first .. 19 last).
    Below the process's own it needs CAP_SYS_NICE or a matching RLIMIT_NICE (``ulimit -e``); when refused,
    or elsewhere than on Linux, logs a warning and returns False (the thread keeps its priority)."""
    import threading

    if not sys.platform.startswith("linux"):
        _log.warning("pipeline.nice: a thread's own priority is Linux only; the scans run at the default")
        return False
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
    except OSError as exc:
        _log.warning("pipeline.nice %d refused (%s): the scans run at the default priority. Below 0 needs "
                     "CAP_SYS_NICE or a RLIMIT_NICE of at least %d (limits.conf 'nice' or 'ulimit -e')",
                     nice, exc.strerror or exc, 20 - nice)
        return False
    return True


def one_blas_thread() -> None:
    """Limit the BLAS libraries loaded so far in this process to one thread (:func:`glassmap.threads.one_thread`)."""
    from glassmap.threads import one_thread

    one_thread()


def one_thread_per_process() -> None:
    """One BLAS / OpenMP thread for this process and the processes it starts: :data:`ONE_THREAD_ENV` unless
    the environment sets those variables already (an explicit setting wins), then :func:`one_blas_thread`
    unless OPENBLAS_NUM_THREADS asks for more."""
    for k, v in ONE_THREAD_ENV.items():
        os.environ.setdefault(k, v)
    if os.environ["OPENBLAS_NUM_THREADS"] == "1":
        one_blas_thread()


def setup_process() -> None:
    """What the ``glassmap`` program does at start, for any process that runs the runtime or a replay (the
    benchmark's child processes too): :func:`one_thread_per_process` and :func:`one_malloc_arena`, before
    any thread starts."""
    one_thread_per_process()
    one_malloc_arena()


def freeze_startup() -> None:
    """Collect once and give the freed memory back to the system (glibc ``malloc_trim``: what an earlier
    run in this process left), then exempt every object alive now from later collections (``gc.freeze``);
    undo with :func:`thaw` at the end of the run."""
    release_memory()
    gc.freeze()


def release_memory() -> None:
    """Collect garbage (reference cycles: an earlier run's processor, grids and threads) and give freed
    memory back to the system (glibc ``malloc_trim``), and the JIT compiler's pages
    (:func:`release_compiler_pages`)."""
    gc.collect()
    if (libc := _libc()) is not None:
        libc.malloc_trim(0)
    release_compiler_pages()


MADV_PAGEOUT = 21  # Linux >= 5.4
COMPILER_LIBRARIES = ("libllvmlite",)  # file names of the JIT compiler's shared libraries (numba's LLVM)


def release_compiler_pages(libraries: tuple[str, ...] = COMPILER_LIBRARIES) -> int:
    """Hand the resident pages of the JIT compiler's shared libraries (file names starting with one of
    ``libraries``) back to the system (``madvise(MADV_PAGEOUT)`` on their mappings in /proc/self/maps): call
    once the kernels are loaded. Pages another process maps as well stay (the kernel skips them). Returns the
    number of bytes of mappings advised (0 off Linux, on kernels without MADV_PAGEOUT, or before numba has
    been imported)."""
    try:
        with open("/proc/self/maps") as f:
            lines = f.read().splitlines()
        madvise = ctypes.CDLL(None).madvise
    except (OSError, AttributeError):
        return 0
    madvise.argtypes, madvise.restype = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int), ctypes.c_int
    done = 0
    for line in lines:
        parts = line.split(maxsplit=5)
        if len(parts) < 6 or not os.path.basename(parts[5]).startswith(libraries):
            continue
        lo, hi = (int(v, 16) for v in parts[0].split("-"))
        if madvise(lo, hi - lo, MADV_PAGEOUT) == 0:
            done += hi - lo
    return done


def thaw() -> None:
    """Make the objects frozen by :func:`freeze_startup` collectable again (``gc.unfreeze``): the run's
    processor, grids and threads hold reference cycles, which stay in memory after the run while frozen
    (several runs in one process, e.g. ``glassmap bench``, would each keep theirs)."""
    gc.unfreeze()


M_ARENA_MAX, M_TRIM_THRESHOLD, M_MMAP_MAX = -8, -1, -4  # glibc's mallopt parameter numbers
GLIBC_TRIM_THRESHOLD, GLIBC_MMAP_MAX = 128 * 1024, 65536  # glibc's defaults


def _libc():
    """glibc's allocator functions with their C types, or None (not glibc)."""
    try:
        libc = ctypes.CDLL(None)
        fns = libc.mallopt, libc.malloc, libc.free, libc.memset, libc.malloc_trim
    except (OSError, AttributeError):
        return None
    mallopt, malloc, free, memset, trim = fns
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    malloc.argtypes, malloc.restype = (ctypes.c_size_t,), ctypes.c_void_p
    free.argtypes, free.restype = (ctypes.c_void_p,), None
    memset.argtypes, memset.restype = (ctypes.c_void_p, ctypes.c_int, ctypes.c_size_t), ctypes.c_void_p
    trim.argtypes, trim.restype = (ctypes.c_size_t,), ctypes.c_int
    return libc


def reserve_heap(nbytes: int) -> bool:
    """Keep freed memory in this process (glibc: large buffers from the heap, free() gives nothing back) and
    write ``nbytes`` of heap once, then free it, so the next buffers reuse pages already mapped. With one
    malloc arena (:func:`one_malloc_arena`) every thread reuses them. Returns False with ``nbytes`` 0 or
    without glibc; undo with :func:`release_heap_reserve`."""
    if nbytes < 0:
        raise ValueError(f"nbytes must be >= 0, got {nbytes}")
    libc = _libc() if nbytes else None
    if libc is None:
        return False
    if libc.mallopt(M_MMAP_MAX, 0) != 1 or libc.mallopt(M_TRIM_THRESHOLD, -1) != 1:  # -1: never trim
        release_heap_reserve()
        return False
    block = libc.malloc(nbytes)
    if not block:
        release_heap_reserve()
        return False
    libc.memset(block, 0, nbytes)
    libc.free(block)
    return True


def release_heap_reserve() -> None:
    """glibc's default limits again (large buffers from fresh mappings, freed memory given back; glibc's
    adjustment of the mapping threshold to the buffers freed stays off once a limit was set) and the heap's
    free memory given back now (``malloc_trim``)."""
    libc = _libc()
    if libc is None:
        return
    libc.mallopt(M_MMAP_MAX, GLIBC_MMAP_MAX)
    libc.mallopt(M_TRIM_THRESHOLD, GLIBC_TRIM_THRESHOLD)
    libc.malloc_trim(0)


def one_malloc_arena() -> bool:
    """One glibc malloc arena for every thread started from now on, unless MALLOC_ARENA_MAX is set (an
    explicit setting wins). Returns True if set; False without glibc (musl, macOS) or with the variable."""
    if "MALLOC_ARENA_MAX" in os.environ:
        return False
    libc = _libc()
    return libc is not None and libc.mallopt(M_ARENA_MAX, 1) == 1
