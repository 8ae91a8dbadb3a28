"""Every fault mode of the emulator, against the real client over a pseudo-terminal."""

from __future__ import annotations

import pytest

from drivers.pioneer.client import PioneerClient
from drivers.pioneer.emulator import EmulatorFaults
from tests.helpers import eventually
from tests.pioneer.conftest import fast_settings
from tests.pioneer.test_client_emulator import assert_pose_matches_controller, settle

pytestmark = pytest.mark.timeout(60)

FAULTS = {
    "corrupted-bytes": EmulatorFaults(corrupt_rate=0.3, seed=1),
    "dropped-bytes": EmulatorFaults(drop_rate=0.3, seed=2),
    "garbage": EmulatorFaults(garbage_rate=0.5, seed=3),
    "still-open": EmulatorFaults(still_open=True),
    "link-loss": EmulatorFaults(link_loss_after=1.0, link_outage=1.0),
    "everything": EmulatorFaults(corrupt_rate=0.1, drop_rate=0.1, garbage_rate=0.2, still_open=True,
                                 link_loss_after=1.5, link_outage=0.5, seed=4),
}


@pytest.mark.parametrize("name", list(FAULTS))
async def test_client_drives_through_the_fault(emulator_factory, name):
    from drivers.pioneer.cli import drive_distance

    faults = FAULTS[name]
    emu, url = await emulator_factory(faults=faults)
    settings = fast_settings(handshake_tries=30, handshake_timeout=1.0)
    async with PioneerClient.connect(url, enable_motors=True, settings=settings) as base:
        if faults.link_loss_after is not None:
            await eventually(lambda: base.stats.reconnects == 1, timeout=20, what="reconnect after the link loss")
            await eventually(lambda: base.state.motors_enabled, what="motors re-enabled")
        await drive_distance(base, 0.4, 0.3)
        await settle(base, emu)
        assert_pose_matches_controller(base.latest, emu)
        st = base.stats
        if faults.corrupt_rate:
            assert st.bad_checksum > 0
        if faults.drop_rate:
            assert st.bad_checksum + st.bad_length + st.parser_timeouts > 0
        if faults.garbage_rate:
            assert st.dropped_bytes > 0
        if faults.still_open:
            assert st.still_open_recoveries >= 1
        if faults.link_loss_after is not None:
            assert st.link_losses == 1 and emu.stats.link_losses == 1
        assert emu.stats.faults_injected > 0 or faults.still_open or faults.link_loss_after is not None


def test_fault_rates_are_validated():
    with pytest.raises(ValueError, match="corrupt_rate"):
        EmulatorFaults(corrupt_rate=1.5)
