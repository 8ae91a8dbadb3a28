"""Hardware-in-the-loop: the real client against the emulated controller over a pseudo-terminal (and TCP)."""

from __future__ import annotations

import math

import pytest

from drivers.pioneer.client import PioneerClient, PioneerSettings
from drivers.pioneer.errors import ClientClosedError, HandshakeTimeout, LinkLostError, UnsupportedRobotError
from drivers.pioneer.packets import SYNC0, SYNC1, SYNC2, Cmd, PacketParser, build_packet, command
from drivers.pioneer.sip import SyncReply, decode_sip
from drivers.transport import open_transport
from glassmap.sim.robot import DiffDriveRobot, OdometryNoise
from tests.helpers import eventually
from tests.pioneer.conftest import SCALE, drive_until, fast_settings

pytestmark = pytest.mark.timeout(60)


def assert_pose_matches_controller(odom, emu, model_mm=1.0):
    """The client's pose equals the controller's dead reckoning up to the SIP quantisation."""
    x, y, yaw = emu.robot.odom_pose
    tol = 1.5 * model_mm / 1000.0
    assert odom.x == pytest.approx(x, abs=tol) and odom.y == pytest.approx(y, abs=tol)
    assert math.remainder(odom.yaw - yaw, 2 * math.pi) == pytest.approx(0.0, abs=0.0016)


async def settle(client, emu):
    """Wait until the robot is at rest and the client has a SIP taken after that."""
    await eventually(lambda: max(map(abs, emu.robot.velocity)) < 1e-9, what="robot at rest")
    n = client.stats.sips
    await eventually(lambda: client.stats.sips >= n + 2, what="two more SIPs")


async def test_handshake_reports_identity_and_stays_disabled(emulator_factory):
    emu, url = await emulator_factory()
    async with PioneerClient.connect(url, settings=fast_settings(read_config=True)) as base:
        assert base.info == SyncReply("glassmap-emulator", "Pioneer", "p3dx-sh")
        assert base.model.dist_conv == 1.0
        assert base.config is not None and base.config.watchdog == 2000
        assert base.state is not None and not base.state.motors_enabled  # real robot: motors off until ENABLE
        assert base.state.battery_volts == pytest.approx(12.6)
        odom = await anext(base.odometry())
        assert odom.stamp > 0 and odom.covariance.shape == (3, 3)
    await eventually(lambda: not emu.is_open, what="CLOSE received")


async def test_close_sends_stop_sequence(emulator_factory):
    emu, url = await emulator_factory()
    base = await PioneerClient.connect(url, enable_motors=True, settings=fast_settings())
    await eventually(lambda: base.state.motors_enabled, what="motors enabled in the SIP")
    await base.set_velocity(0.3, 0.2)
    await eventually(lambda: emu.robot.velocity[0] > 0.05, what="robot moving")
    await base.close()
    await eventually(lambda: not emu.is_open, what="CLOSE received")
    tail = [(c.cmd, c.arg) for c in emu.received[-4:]]
    assert tail == [(Cmd.VEL, 0), (Cmd.RVEL, 0), (Cmd.ENABLE, 0), (Cmd.CLOSE, None)]
    assert not emu.is_open and not emu.motors_enabled
    with pytest.raises(ClientClosedError):
        await base.set_velocity(0.1, 0.0)
    await base.close()  # idempotent


@pytest.mark.parametrize("subclass,mm", [("p3dx-sh", 1.0), ("p3dx", 0.485)])
async def test_drive_a_square_and_read_back_a_consistent_pose(emulator_factory, subclass, mm):
    from drivers.pioneer.cli import drive_square

    emu, url = await emulator_factory(subclass=subclass)
    async with PioneerClient.connect(url, enable_motors=True, settings=fast_settings()) as base:
        await drive_square(base, 0.4, 0.4, math.radians(60))
        await settle(base, emu)
        odom = base.latest
        assert_pose_matches_controller(odom, emu, mm)
        # the square closes up to the simulator's odometry error and the controller's overshoot
        assert math.hypot(odom.x, odom.y) < 0.1
        tr = base.session.tracker
        assert 1.58 < tr.distance < 1.8 and 2 * math.pi - 0.05 < tr.rotation < 2 * math.pi + 1.0
        assert abs(odom.yaw) < math.radians(5)
        # covariance has grown with 2 m and a full turn
        assert odom.covariance[0, 0] > 0 and odom.covariance[1, 1] > 0
        assert math.sqrt(odom.covariance[2, 2]) > 0.05
        assert base.stats.bad_checksum == 0 and base.stats.command_timeouts == 0


@pytest.mark.parametrize("start,distance", [(-0.2, 0.5), (0.2, -0.5)], ids=["forward", "backward"])
@pytest.mark.parametrize("real_robot", [True, False], ids=["real", "simulator"])
async def test_odometry_across_the_position_wrap_live(emulator_factory, start, distance, real_robot):
    from drivers.pioneer.cli import drive_distance

    robot = DiffDriveRobot(noise=OdometryNoise.none(), odom0=(start, 0.0, 0.0))
    emu, url = await emulator_factory(robot=robot, subclass="p3dx", real_robot=real_robot)
    async with PioneerClient.connect(url, enable_motors=True, settings=fast_settings()) as base:
        assert base.latest.x == pytest.approx(start, abs=0.001)
        await drive_distance(base, distance, 0.4)
        await settle(base, emu)
        assert_pose_matches_controller(base.latest, emu, 0.485)
        assert base.latest.x == pytest.approx(start + distance, abs=0.05)
        assert base.session.tracker.max_step_units < 200  # no 15/16-bit jump was integrated


async def test_simulator_deviations_are_handled(emulator_factory):
    emu, url = await emulator_factory(real_robot=False)
    async with PioneerClient.connect(url, settings=fast_settings()) as base:
        assert base.state.motors_enabled  # this simulator starts with motors on
        await drive_until(base, 0.3, 0.0, lambda: emu.robot.velocity[0] > 0.2, what="moving")
        assert base.last_sip is not None and not base.last_sip.moving  # 0x32 even while moving
        assert len(base.last_sip.sonar) == 16 and len(base.state.sonar) == 16
        await base.stop()
        await settle(base, emu)
        assert_pose_matches_controller(base.latest, emu)


async def test_velocities_are_per_host_second_like_the_stamps(emulator_factory):
    """An emulator SCALE times faster than real time: the SIP reports 0.3 m/s of emulated time, the client
    reports SCALE x 0.3 m/s, consistent with the host stamps (what a pose extrapolation multiplies by)."""
    emu, url = await emulator_factory(real_robot=False)
    async with PioneerClient.connect(url, settings=fast_settings()) as base:
        await drive_until(base, 0.3, 0.0, lambda: emu.robot.velocity[0] > 0.29, what="at speed")
        await drive_until(base, 0.3, 0.0, lambda: base.latest.v > 0.29 * SCALE, what="reported at speed")
        assert base.latest.v == pytest.approx(0.3 * SCALE, rel=0.05)
        await base.stop()


async def test_real_robot_reports_moving_and_partial_sonar(emulator_factory):
    emu, url = await emulator_factory()
    async with PioneerClient.connect(url, enable_motors=True, settings=fast_settings()) as base:
        await base.send_command(Cmd.SONAR, 1)
        await drive_until(base, 0.3, 0.0, lambda: base.last_sip.moving, what="SIP type 0x33")
        assert 0 < len(base.last_sip.sonar) < 16
        await eventually(lambda: len(base.state.sonar) == 16, what="all sonar seen over several SIPs")
        await base.request_encoders(1)
        await eventually(lambda: base.encoders is not None, what="ENCODER packet")


async def test_watchdog_stops_a_robot_left_without_packets(emulator_factory):
    emu, url = await emulator_factory()
    t = await open_transport(url)
    parser = PacketParser()
    try:
        for pid in (SYNC0, SYNC1, SYNC2):
            await t.write(build_packet(pid))
            await eventually(lambda: emu._session >= pid + 1, what=f"SYNC{pid} accepted")
        await t.write(command(Cmd.OPEN) + command(Cmd.ENABLE, 1) + command(Cmd.VEL, 300))
        await eventually(lambda: emu.robot.velocity[0] > 0.25, what="moving")
        # now silence: after 2 s (emulated) the controller stops the robot by itself
        await eventually(lambda: emu.stats.watchdog_trips == 1, what="watchdog trip")
        await eventually(lambda: emu.robot.velocity[0] == 0.0, what="stopped by the watchdog")
        assert emu.commanded_velocity[0] == pytest.approx(0.3)  # the setpoint itself is kept ...
        await t.write(command(Cmd.PULSE))
        await eventually(lambda: emu.robot.velocity[0] > 0.25, what="resumed")  # ... and resumes with packets
        # the SIP stream confirms both
        sips = [decode_sip(p.pid, p.payload) for p in parser.feed(await t.read()) if p.pid in (0x32, 0x33)]
        assert all(s.motors_enabled for s in sips)
    finally:
        await t.write(command(Cmd.ENABLE, 0) + command(Cmd.CLOSE))
        await t.close()


async def test_simulator_watchdog_only_logs(emulator_factory):
    emu, url = await emulator_factory(real_robot=False)
    t = await open_transport(url)
    try:
        for pid in (SYNC0, SYNC1, SYNC2):
            await t.write(build_packet(pid))
            await eventually(lambda: emu._session >= pid + 1, what=f"SYNC{pid} accepted")
        await t.write(command(Cmd.OPEN) + command(Cmd.VEL, 200))
        await eventually(lambda: emu.stats.watchdog_trips == 1, what="watchdog trip")
        assert emu.robot.velocity[0] == pytest.approx(0.2)
    finally:
        await t.close()


async def test_client_keepalive_prevents_the_watchdog(emulator_factory):
    emu, url = await emulator_factory()
    async with PioneerClient.connect(url, enable_motors=True, settings=fast_settings()) as base:
        t0 = emu.now()
        await eventually(lambda: emu.now() - t0 > 3 * emu.watchdog, what="three watchdog periods")
        assert emu.stats.watchdog_trips == 0
        assert base.stats.keepalives > 0
        assert sum(c.cmd == Cmd.PULSE for c in emu.received) > 0


async def test_command_timeout_stops_the_robot(emulator_factory):
    emu, url = await emulator_factory()
    async with PioneerClient.connect(url, enable_motors=True, settings=fast_settings()) as base:
        await base.set_velocity(0.4, 0.0)  # ... and never again
        await eventually(lambda: emu.robot.velocity[0] > 0.1, what="moving")
        await eventually(lambda: base.stats.command_timeouts == 1, what="command timeout")
        assert base.setpoint == (0.0, 0.0)
        await eventually(lambda: emu.commanded_velocity == (0.0, 0.0), what="VEL 0 received")
        await eventually(lambda: emu.robot.velocity[0] == 0.0, what="robot stopped")
        assert emu.stats.watchdog_trips == 0  # the client stopped it, not the robot's watchdog


async def test_velocity_is_clamped_to_the_limits(emulator_factory):
    emu, url = await emulator_factory()
    async with PioneerClient.connect(url, enable_motors=True,
                                     settings=fast_settings(max_v=0.3, max_omega=math.radians(20))) as base:
        await base.set_velocity(5.0, -3.0)
        assert base.setpoint == pytest.approx((0.3, -math.radians(20)))
        await eventually(lambda: any(c.cmd == Cmd.RVEL and c.arg == -20 for c in emu.received), what="RVEL")
        assert [c.arg for c in emu.received if c.cmd == Cmd.VEL][-1] == 300
        with pytest.raises(ValueError):
            await base.set_velocity(float("nan"), 0.0)


async def test_estop(emulator_factory):
    emu, url = await emulator_factory()
    async with PioneerClient.connect(url, enable_motors=True, settings=fast_settings()) as base:
        await drive_until(base, 0.4, 0.0, lambda: emu.robot.velocity[0] > 0.2, what="moving")
        await base.estop()
        await eventually(lambda: base.state.estop, what="e-stop flag in the SIP")
        await eventually(lambda: emu.robot.velocity[0] == 0.0, what="stopped")
        assert base.setpoint == (0.0, 0.0)


async def test_bumpers_and_stall_are_exposed(emulator_factory):
    emu, url = await emulator_factory()
    async with PioneerClient.connect(url, settings=fast_settings()) as base:
        emu.stall_bumpers = 0x0001 | (0b101 << 9) | (0b10 << 1)
        await eventually(lambda: base.state.bumped, what="bumper bits")
        st = base.state
        assert st.left_stall and not st.right_stall and st.stalled
        assert st.front_bumpers == 0b101 and st.rear_bumpers == 0b10


async def test_unknown_subclass_is_refused_with_advice(emulator_factory):
    emu, url = await emulator_factory()
    emu.identity = SyncReply("x", "Pioneer", "p3at-sh")
    with pytest.raises(UnsupportedRobotError, match="p3at-sh"):
        await PioneerClient.connect(url, settings=fast_settings())
    async with PioneerClient.connect(url, settings=fast_settings(model="p3dx-sh")) as base:
        assert base.model.subclass == "p3dx-sh"


async def test_silent_port_gives_up_after_bounded_retries(tmp_path):
    from drivers.endpoints import PtyEndpoint

    ep = PtyEndpoint(str(tmp_path))
    try:
        with pytest.raises(HandshakeTimeout, match="no answer to SYNC0 after 3 tries"):
            await PioneerClient.connect(f"serial://{ep.path}", PioneerSettings(handshake_tries=3, handshake_timeout=0.1))
    finally:
        ep.close()


@pytest.mark.parametrize("link", ["pty", "tcp"])
async def test_reconnect_after_link_loss_never_resumes_motion(emulator_factory, link):
    emu, url = await emulator_factory(link)
    async with PioneerClient.connect(url, enable_motors=True, settings=fast_settings(sip_timeout=3.0)) as base:
        await drive_until(base, 0.3, 0.0, lambda: emu.robot.velocity[0] > 0.2, what="moving")
        emu.link_loss(outage=2.0)
        await eventually(lambda: not base.connected, what="link loss noticed")
        with pytest.raises(LinkLostError):
            await base.set_velocity(0.3, 0.0)
        await base.wait_connected(timeout=20)
        assert base.stats.link_losses == 1 and base.stats.reconnects == 1
        if link == "pty":  # the controller stayed open through the cable pull: the client closed it first
            assert base.stats.still_open_recoveries == 1
        assert base.setpoint == (0.0, 0.0)
        n = base.stats.sips
        await eventually(lambda: base.stats.sips > n + 10, what="SIPs after reconnecting")
        assert emu.robot.velocity == (0.0, 0.0) and emu.commanded_velocity == (0.0, 0.0)
        await eventually(lambda: base.state.motors_enabled, what="motors re-enabled at rest")
        # the caller may drive again
        await drive_until(base, 0.2, 0.0, lambda: emu.robot.velocity[0] > 0.1, what="moving again")
        await base.stop()
        await settle(base, emu)
        assert_pose_matches_controller(base.latest, emu)


async def test_taps_survive_reconnection(emulator_factory):
    from drivers.capture import CaptureRecorder

    emu, url = await emulator_factory()
    rec = CaptureRecorder("pioneer")
    async with PioneerClient.connect(url, taps=[rec], settings=fast_settings()) as base:
        emu.link_loss(outage=1.0)
        await eventually(lambda: not base.connected, what="link loss noticed")
        await base.wait_connected(timeout=20)
    tx = rec.capture.tx_bytes()
    assert tx.count(build_packet(SYNC2)) >= 2  # one handshake per link, both recorded
    assert PacketParser().feed(rec.capture.rx_bytes())  # and what the robot sent


async def test_no_reconnect_ends_odometry_with_the_error(emulator_factory):
    emu, url = await emulator_factory()
    base = await PioneerClient.connect(url, settings=fast_settings(reconnect=False))
    try:
        emu.link_loss(outage=5.0)
        with pytest.raises(LinkLostError):
            async for _ in base.odometry():
                pass
    finally:
        await base.close()


async def test_switch_to_a_higher_baud_rate(emulator_factory):
    emu, url = await emulator_factory()
    async with PioneerClient.connect(url, settings=fast_settings(high_baud=38400)) as base:
        assert emu.hostbaud == 2  # HOSTBAUD code of 38400
        n = base.stats.sips
        await eventually(lambda: base.stats.sips > n + 3, what="SIPs at the new speed")
        assert base.url == url  # reconnects start again at the power-up speed


async def test_emulator_obeys_vel2_head_and_seto(emulator_factory):
    from drivers.pioneer.packets import vel2_value

    robot = DiffDriveRobot(noise=OdometryNoise.none())
    emu, url = await emulator_factory(robot=robot)
    async with PioneerClient.connect(url, enable_motors=True, settings=fast_settings(command_timeout=None)) as base:
        # VEL2: left -5, right +5 (x 20 mm/s): turn in place CCW at (200 / 2) * 0.0056 rad/s
        await base.send_command(Cmd.VEL2, vel2_value(-5, 5))
        await eventually(lambda: emu.commanded_velocity == pytest.approx((0.0, 100 * 0.0056)), what="VEL2")
        await base.send_command(Cmd.STOP)
        # HEAD 90: the controller turns to 90 deg by itself
        await base.send_command(Cmd.HEAD, 90)
        await eventually(lambda: abs(math.remainder(emu.robot.odom_pose[2] - math.pi / 2, 2 * math.pi)) < 0.02
                         and abs(emu.robot.velocity[1]) < 1e-3, timeout=20, what="heading 90 deg reached")
        await settle(base, emu)
        assert base.latest.yaw == pytest.approx(math.pi / 2, abs=0.03)
        assert base.last_sip.control == pytest.approx(1024, abs=1)  # heading setpoint in angle units
        # SETO: the controller restarts its odometry at zero (the tracker then re-anchors)
        await base.send_command(Cmd.STOP)  # leaves heading mode
        await base.send_command(Cmd.SETO)
        n = base.stats.sips
        await eventually(lambda: base.stats.sips > n + 2, what="SIPs after SETO")
        base.session.tracker.reanchor()
        n = base.stats.sips
        await eventually(lambda: base.stats.sips > n + 1, what="SIP to anchor on")
        assert (base.latest.x, base.latest.y, base.latest.yaw) == pytest.approx((0.0, 0.0, 0.0), abs=0.002)


async def test_silent_tcp_server_gets_a_tcp_hint_not_a_serial_one():
    import asyncio

    async def silent(reader, writer):
        await reader.read()  # accept, read, never answer
        writer.close()

    server = await asyncio.start_server(silent, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        with pytest.raises(HandshakeTimeout) as err:
            await PioneerClient.connect(f"tcp://127.0.0.1:{port}", PioneerSettings(handshake_tries=2, handshake_timeout=0.1))
        msg = str(err.value)
        assert "listening on that port" in msg
        assert "9600" not in msg and "cable" not in msg and "SERIAL" not in msg
    finally:
        server.close()


@pytest.mark.parametrize("resume", [False, True], ids=["stops", "continues"])
async def test_scripted_drive_stops_and_reports_after_a_reconnect(emulator_factory, resume):
    """`glassmap pioneer drive` must not set off again by itself once the client has re-opened a lost link."""
    import asyncio

    from drivers.pioneer.cli import drive_distance
    from drivers.pioneer.motion_guard import MotionInterrupted

    emu, url = await emulator_factory()
    async with PioneerClient.connect(url, enable_motors=True, settings=fast_settings(sip_timeout=3.0)) as base:
        drive = asyncio.ensure_future(drive_distance(base, 3.0, 0.3, timeout=60, resume=resume))
        await eventually(lambda: emu.robot.distance > 0.3, what="driving")
        emu.link_loss(outage=1.0)
        if not resume:
            with pytest.raises(MotionInterrupted, match="continue-after-reconnect"):
                await asyncio.wait_for(drive, 30)
            n = base.stats.sips
            await eventually(lambda: base.stats.sips > n + 10, what="SIPs after the reconnect")
            assert emu.robot.velocity == (0.0, 0.0) and emu.commanded_velocity == (0.0, 0.0)
            assert emu.robot.distance < 2.0
        else:
            await asyncio.wait_for(drive, 40)
            await settle(base, emu)
            assert base.stats.reconnects == 1
            assert emu.robot.distance == pytest.approx(3.0, abs=0.15)
