"""Process-wide settings of runtime.tuning, each checked in a fresh interpreter (they change the process)."""

import json
import platform
import os
import subprocess
import sys
from pathlib import Path

import pytest

from runtime.tuning import one_malloc_arena

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


_ARENAS = """
import ctypes, os, sys, tempfile, threading
from runtime.tuning import one_malloc_arena
if sys.argv[1] == "one":
    assert one_malloc_arena()
keep = []
def work():
    keep.append([ctypes.create_string_buffer(200_000) for _ in range(5)])  # glibc malloc, not pymalloc
ts = [threading.Thread(target=work) for _ in range(4)]
[t.start() for t in ts]; [t.join() for t in ts]
libc = ctypes.CDLL(None)
libc.fopen.restype = ctypes.c_void_p
path = os.path.join(tempfile.mkdtemp(), "info.xml")
fp = libc.fopen(path.encode(), b"w")
libc.malloc_info(0, ctypes.c_void_p(fp)); libc.fclose(ctypes.c_void_p(fp))
print(open(path).read().count("<heap nr="))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_one_malloc_arena_makes_threads_share_one_arena():
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_ARENA_MAX"}

    def heaps(mode: str) -> int:
        out = subprocess.run([sys.executable, "-c", _ARENAS, mode], capture_output=True, text=True, env=env,
                             check=True)
        return int(out.stdout)

    assert heaps("one") == 1
    assert heaps("default") > 1


def test_an_explicit_malloc_arena_max_wins(monkeypatch):
    monkeypatch.setenv("MALLOC_ARENA_MAX", "4")
    assert one_malloc_arena() is False


_THAW = """
import gc, weakref
from runtime.tuning import freeze_startup, thaw
class Node: pass
a = Node(); a.self = a  # a reference cycle, alive at the freeze, as a run's processor is
ref = weakref.ref(a)
freeze_startup()
del a
gc.collect()
frozen_kept = ref() is not None
thaw()
gc.collect()
print(frozen_kept, ref() is None, gc.get_freeze_count())
"""


def test_thaw_lets_the_collector_free_what_a_run_froze():
    out = subprocess.run([sys.executable, "-c", _THAW], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["True", "True", "0"]


_COMPILER_PAGES = """
import json
import numba
from runtime.tuning import COMPILER_LIBRARIES, release_compiler_pages

def private_clean_kib():  # the compiler library's pages that only this process maps
    total, name = 0, ""
    for line in open("/proc/self/smaps"):
        head = line.split()
        if "-" in head[0] and len(head) >= 5 and ":" not in head[0]:
            name = head[5] if len(head) > 5 else ""
        elif head[0] == "Private_Clean:" and any(lib in name for lib in COMPILER_LIBRARIES):
            total += int(head[1])
    return total

@numba.njit
def before(x):
    return x * 2 + 1

first = before(20)
loaded = private_clean_kib()
advised = release_compiler_pages()
left = private_clean_kib()

@numba.njit
def after(x):  # compiled after the release: LLVM's pages come back as it needs them
    return x - 3

print(json.dumps({"first": first, "again": before(5), "new": after(10), "advised": advised,
                  "loaded": loaded, "left": left}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/maps and MADV_PAGEOUT are Linux's")
def test_the_jit_compilers_pages_go_back_and_kernels_still_compile_and_run(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    out = json.loads(subprocess.run([sys.executable, "-c", _COMPILER_PAGES], capture_output=True, text=True,
                                    check=True, env=env).stdout)
    assert (out["first"], out["again"], out["new"]) == (41, 11, 7)
    assert out["advised"] > 10 * 2 ** 20  # the LLVM library's mappings were found (~160 MB of them)
    # the pages only this process maps leave it (tens of MiB in a fresh interpreter; pages another process
    # maps too, e.g. a test runner that has run kernels, are shared and stay: the kernel skips those)
    assert out["left"] <= 4 * 1024


def _on_tmpfs(path) -> bool:
    """Whether ``path`` lies on a tmpfs (its pages are shared memory: without swap they cannot be paged out)."""
    best, fstype = "", ""
    with open("/proc/self/mounts") as f:
        for line in f:
            mount, kind = line.split()[1:3]
            if str(path).startswith(mount) and len(mount) > len(best):
                best, fstype = mount, kind
    return fstype == "tmpfs"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/maps and MADV_PAGEOUT are Linux's")
def test_release_compiler_pages_pages_out_a_mapped_library_file_only_this_process_maps(tmp_path):
    # the numba probe above shares LLVM's pages with a test runner that has run kernels (they then stay):
    # a file of our own, mapped by this process only, shows the release itself. It must lie on a disk: a
    # tmpfs file's pages are shared memory, which cannot be paged out without swap. tmp_path is often a
    # tmpfs; the checkout (where this test lives), /var/tmp or the home directory is then the disk to use.
    import tempfile

    candidates = (tmp_path, Path(__file__).resolve().parent, Path("/var/tmp"), Path.home())
    base = next((d for d in candidates if d.is_dir() and os.access(d, os.W_OK) and not _on_tmpfs(d)), None)
    if base is None:
        pytest.skip(reason="no writable directory on a disk (all on tmpfs): nothing can show the page-out")
    with tempfile.TemporaryDirectory(dir=base, prefix="pageout-") as d:
        _page_out_own_library(Path(d))


def _page_out_own_library(tmp_path: Path) -> None:
    lib = tmp_path / "libfakecompiler.so"
    lib.write_bytes(os.urandom(8 * 2 ** 20))
    import mmap

    from runtime.tuning import release_compiler_pages

    def resident_kib() -> int:
        total, name = 0, ""
        with open("/proc/self/smaps") as f:
            for line in f:
                head = line.split()
                if "-" in head[0] and ":" not in head[0]:
                    name = head[5] if len(head) > 5 else ""
                elif head[0] == "Rss:" and name == str(lib):
                    total += int(head[1])
        return total

    with open(lib, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
        assert sum(m[i] for i in range(0, len(m), 4096)) >= 0  # every page touched
        before = resident_kib()
        assert release_compiler_pages(("libfakecompiler",)) == len(m)
        after = resident_kib()
    assert before >= 7 * 1024 and after <= 256


_RESERVE = """
import ctypes, resource, sys
ctypes.CDLL(None).prctl(41, 1, 0, 0, 0)  # PR_SET_THP_DISABLE: 4 KiB pages, one fault each, whatever THP's setting
import numpy as np
from runtime.tuning import release_heap_reserve, reserve_heap
class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                               "fsmblks", "uordblks", "fordblks", "keepcost")]
libc = ctypes.CDLL(None)
libc.mallinfo2.restype = MallInfo2
reserved = reserve_heap(64 << 20) if sys.argv[1] == "reserve" else False
held = libc.mallinfo2().fordblks
faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
layers = [np.ones((1200, 1200), np.float32) for _ in range(6)]  # a grown grid's layers, written
faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - faults
del layers
release_heap_reserve()
print(reserved, held, faults, libc.mallinfo2().fordblks)
"""


def _glibc_version() -> tuple[int, ...]:
    name, version = platform.libc_ver()
    return tuple(int(v) for v in version.split(".")[:2]) if name == "glibc" and version else ()


@pytest.mark.skipif(not sys.platform.startswith("linux") or _glibc_version() < (2, 33),
                    reason="glibc >= 2.33 (mallinfo2)")
def test_reserve_heap_keeps_written_pages_for_the_next_buffers():
    def run(mode: str) -> list[str]:
        out = subprocess.run([sys.executable, "-c", _RESERVE, mode], capture_output=True, text=True, check=True)
        return out.stdout.split()

    reserved, held, faults, after = run("reserve")
    assert reserved == "True" and int(held) >= 64 << 20  # the reserve stays in the process, free
    _, _, plain_faults, _ = run("plain")
    assert int(plain_faults) > 1000  # 33 MiB of new buffers written: new pages ...
    assert int(faults) < int(plain_faults) // 10  # ... but hardly any when they reuse the reserve
    assert int(after) < 16 << 20  # release_heap_reserve gave the free memory back


def test_reserve_heap_of_nothing_changes_nothing():
    from runtime.tuning import reserve_heap

    assert reserve_heap(0) is False
    with pytest.raises(ValueError, match="nbytes"):
        reserve_heap(-1)
