"""glassmap bench's memory figures: each run's own peak."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from runtime.bench import peak_rss_mib, reset_peak_rss


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/clear_refs is Linux only")
def test_the_peak_of_a_later_run_does_not_include_an_earlier_larger_one():
    big = np.ones(80 * 2**20 // 8)  # 80 MiB, touched: resident
    big_peak = peak_rss_mib()
    del big  # a large block goes back to the system at once (mmap)
    assert reset_peak_rss()
    small = np.ones(8 * 2**20 // 8)
    assert peak_rss_mib() < big_peak - 50
    del small
