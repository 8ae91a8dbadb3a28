"""The per-stage CPU table of ``glassmap bench --stages``."""

from runtime.processor import MappingProcessor
from runtime.stageprof import STAGES, stage_profile
from tests.runtime.test_bad_input import recording


def test_stage_profile_times_every_scan_and_restores_the_functions(tmp_path):
    before = MappingProcessor.__dict__["process"]
    t = stage_profile(str(recording(tmp_path / "rec.mcap", n=12)))
    assert MappingProcessor.__dict__["process"] is before  # unwrapped again
    whole, glass = STAGES[0][1], "glass path (GlassMapper.process)"
    assert t.scans == 12 and t.calls[whole] == 12 and t.calls[glass] == 12
    # the replay's warm-up is not counted; every scan is classified (the wrappers sit where the calls are)
    for stage in ("incidence angles (split-merge)", "classifier features", "classifier network"):
        assert t.calls[stage] == 12, stage
    assert 0 < t.cpu[glass] <= t.cpu[whole] <= t.process_cpu
    # the processing holds the whole scans; reading is timed apart from it, in the same thread
    assert t.cpu[whole] <= t.processing_cpu <= t.process_cpu and 0 < t.reader_cpu <= t.process_cpu
    table = t.table().splitlines()
    # + the process's CPU per scan, its three parts (processing, reading, other threads), that as scans/s
    assert len(table) == 2 + len(STAGES) + 5
    assert table[-1].endswith(f"| {t.scans / t.process_cpu:.0f} | |")
    assert all(label in t.table() for _, label, _, _ in STAGES)
