"""Indentation rig: configs, G-code stage, force gauge, presses, CLI.

Every device test talks to a simulated rig over real pseudo-terminals opened with pyserial.
Expected values come from planted parameters (the true stage frame, the force function, the
gauge offset/sign/units) or are worked out by hand, never from the code under test.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import serial
from typer.testing import CliRunner

from tactile_deploy.calibration.rig import (
    ForceGauge,
    GaugeError,
    GCodeStage,
    IndentationRig,
    RigConfig,
    RigConfigError,
    RigConnectionError,
    RigTimeoutError,
    SoftLimitError,
    StageConfig,
    StageError,
    StageFrame,
    load_rig_config,
    make_stage,
    parse_position,
    rig_config_from_dict,
    save_rig_config,
)
from tactile_deploy.calibration.rig.cli import EXIT_FORCE_LIMITED, rig_app
from tactile_deploy.calibration.rig.simulated import HertzForce, SimulatedRig

# The true placement of the virtual sensor: stage X runs against sensor x.
FRAME = StageFrame(
    sensor_origin_x_mm=42.0,
    sensor_origin_y_mm=37.5,
    z_touch_mm=18.0,
    axis_sign_x=-1,
    axis_sign_y=1,
    axis_sign_z=1,
)
K_N_PER_MM1P5 = 2.3


def planted_force(indentation_mm: float, x_mm: float, y_mm: float) -> float:
    """A force law that depends on x and y, so swapped or mis-signed axes show."""
    return K_N_PER_MM1P5 * max(0.0, indentation_mm) ** 1.5 * (1.0 + 0.02 * x_mm - 0.01 * y_mm)


# Replies over a pseudo-terminal take well under a millisecond; faults are timed with margins
# of at least 0.1 s around these timeouts.
FAST_STAGE = {"timeout_s": 0.2, "motion_timeout_s": 0.4, "retries": 2}
FAST_GAUGE = {"timeout_s": 0.2, "retries": 2, "tare_samples": 2}


def _open_fds() -> set[str]:
    return set(os.listdir("/proc/self/fd"))


class Bench:
    """Starts simulated rigs and devices, and closes all of them."""

    def __init__(self):
        self.sims: list[SimulatedRig] = []
        self.devices: list = []

    def sim(self, force_fn=planted_force, frame=FRAME, **gauge_options) -> SimulatedRig:
        sim = SimulatedRig(force_fn, frame=frame, **gauge_options)
        sim.start()
        self.sims.append(sim)
        return sim

    def config(self, sim: SimulatedRig, stage=None, gauge=None, **rig) -> RigConfig:
        return sim.rig_config(
            stage={**FAST_STAGE, **(stage or {})}, gauge={**FAST_GAUGE, **(gauge or {})}, **rig
        )

    def connect(self, device):
        self.devices.append(device)
        device.connect()
        return device

    def close(self):
        for device in self.devices:
            device.disconnect()
        for sim in self.sims:
            sim.stop()


@pytest.fixture
def bench():
    fds_before = _open_fds()
    threads_before = set(threading.enumerate())
    b = Bench()
    try:
        yield b
    finally:
        b.close()
    leaked_threads = [t for t in threading.enumerate() if t not in threads_before]
    assert leaked_threads == [], f"threads left running: {leaked_threads}"
    assert _open_fds() == fds_before, "file descriptors left open"


# -- frames and configs ---------------------------------------------------------------------


def test_frame_mapping_by_hand():
    # x: 42 - 3 = 39; y: 37.5 + (-2) = 35.5; z: 18 + (-1.5) = 16.5
    assert FRAME.sensor_to_stage(3.0, -2.0, -1.5) == pytest.approx((39.0, 35.5, 16.5))
    assert FRAME.stage_to_sensor(39.0, 35.5, 16.5) == pytest.approx((3.0, -2.0, -1.5))
    # Domed surface 0.4 mm below the plane: 1 mm deep means tip at z = -1.4.
    assert FRAME.contact_to_stage(3.0, -2.0, 1.0, surface_z_mm=-0.4) == pytest.approx(
        (39.0, 35.5, 16.6)
    )
    down = StageFrame(z_touch_mm=30.0, axis_sign_z=-1)
    assert down.sensor_to_stage(0.0, 0.0, -2.0)[2] == pytest.approx(32.0)


def test_config_save_load_roundtrip(tmp_path):
    cfg = rig_config_from_dict(
        {
            "stage": {"port": "/dev/ttyUSB0", "frame": FRAME.model_dump(), "retries": 4},
            "gauge": {"port": "socket://10.0.0.2:4001", "newtons_per_unit": 9.80665},
            "force_limit_n": 7.5,
        }
    )
    path = tmp_path / "rig.json"
    path.write_text("old content")
    save_rig_config(cfg, path)
    assert load_rig_config(path) == cfg
    assert json.loads(path.read_text())["stage"]["frame"]["axis_sign_x"] == -1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.json"]  # no temp file left


def test_docs_example_config_is_valid():
    text = (Path(__file__).parents[1] / "docs" / "rig.md").read_text()
    block = text.split("```json\n", 1)[1].split("```", 1)[0]
    cfg = rig_config_from_dict(json.loads(block), source="docs/rig.md")
    assert cfg.stage.port == "/dev/ttyUSB0" and cfg.gauge.port == "/dev/ttyUSB1"


def test_configs_and_package_import_no_hardware_library():
    code = "import sys, tactile_deploy.calibration.rig; assert 'serial' not in sys.modules, 'serial imported'"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def _write(tmp_path, data) -> str:
    path = tmp_path / "bad.json"
    path.write_text(data if isinstance(data, str) else json.dumps(data))
    return str(path)


def test_config_errors_name_file_field_expected_actual(tmp_path):
    base = {"stage": {"port": "/dev/a"}, "gauge": {"port": "/dev/b"}}

    path = _write(tmp_path, {**base, "stage": {"port": "/dev/a", "baudrate": -5}})
    with pytest.raises(RigConfigError) as err:
        load_rig_config(path)
    text = str(err.value)
    assert path in text and "stage.baudrate" in text and "greater than 0" in text and "-5" in text

    with pytest.raises(RigConfigError, match=r"field 'gauge\.colour': unknown field"):
        load_rig_config(_write(tmp_path, {**base, "gauge": {"port": "/dev/b", "colour": 1}}))

    with pytest.raises(RigConfigError, match=r"field 'stage': required"):
        load_rig_config(_write(tmp_path, {"gauge": {"port": "/dev/b"}}))

    with pytest.raises(RigConfigError, match=r"not valid JSON at line 2, column 1"):
        load_rig_config(_write(tmp_path, '{"stage":\n}'))

    with pytest.raises(RigConfigError, match=r"expected a JSON object.*got list"):
        load_rig_config(_write(tmp_path, "[1, 2]"))

    with pytest.raises(RigConfigError, match=r"no such rig config file"):
        load_rig_config(tmp_path / "missing.json")

    with pytest.raises(RigConfigError, match=r"z_limits_mm=\[5\.0, 1\.0\] must be \[min, max\]"):
        rig_config_from_dict({**base, "stage": {"port": "/dev/a", "z_limits_mm": [5, 1]}})

    with pytest.raises(RigConfigError, match=r"stage Z=80\.0 mm .* outside z_limits_mm"):
        rig_config_from_dict(
            {**base, "stage": {"port": "/dev/a", "frame": {"z_touch_mm": 80.0}}}
        )

    with pytest.raises(RigConfigError, match=r"reply_regex .* has no capture group"):
        rig_config_from_dict({**base, "gauge": {"port": "/dev/b", "reply_regex": r"\d+ N"}})

    with pytest.raises(RigConfigError, match=r"approach_clearance_mm=6\.0 must not exceed"):
        rig_config_from_dict({**base, "approach_clearance_mm": 6.0})

    with pytest.raises(RigConfigError, match=r"unknown stage kind 'grbl'; known kinds: gcode"):
        make_stage(StageConfig(port="/dev/a", kind="grbl"))


def test_parse_position():
    line = "X:12.50 Y:-3.25 Z:7.00 E:0.00 Count X:1000 Y:-260 Z:2800"
    assert parse_position(line) == (12.5, -3.25, 7.0)
    assert parse_position("X:1 Y:2 Z:.5") == (1.0, 2.0, 0.5)
    assert parse_position("X:1.00 Y:\ufffd\ufffd Z:3.00") is None
    assert parse_position("ok") is None


# -- stage -----------------------------------------------------------------------------------


def _stage(bench, sim, **overrides) -> GCodeStage:
    return bench.connect(GCodeStage(bench.config(sim, stage=overrides).stage))


def test_stage_moves_homes_and_reads_back_over_pty(bench):
    sim = bench.sim()
    stage = _stage(bench, sim)
    assert stage.home() == pytest.approx(sim.stage.home_mm)
    stage.move_to(12.5, 30.25, 22.0)
    assert sim.stage.position_mm == pytest.approx((12.5, 30.25, 22.0))
    assert stage.position() == pytest.approx((12.5, 30.25, 22.0))
    stage.move_to(z_mm=40.0, rapid=True)
    assert sim.stage.position_mm == pytest.approx((12.5, 30.25, 40.0))
    assert sim.stage.feed_mm_min == pytest.approx(1200.0)
    received = sim.stage.received
    assert received[:2] == ["G21", "G90"]
    assert "G1 X12.5 Y30.25 Z22 F60" in received and "G0 Z40 F1200" in received


def test_stage_port_is_a_plain_serial_device(bench):
    sim = bench.sim()
    with serial.Serial(sim.stage_port, 115200, timeout=1.0) as ser:
        ser.write(b"G1 X3 Y4 Z5\nM114\n")
        lines = [ser.readline() for _ in range(3)]
    assert lines[0] == b"ok\n"
    assert lines[1].startswith(b"X:3.00 Y:4.00 Z:5.00 E:0.00 Count")
    assert lines[2] == b"ok\n"


def test_stage_dropped_reply_is_retried(bench):
    sim = bench.sim()
    stage = _stage(bench, sim)
    sim.stage.inject("drop", match="G1")
    stage.move_to(10.0, 10.0, 30.0)
    assert sim.stage.received.count("G1 X10 Y10 Z30 F60") == 2
    assert stage.position() == pytest.approx((10.0, 10.0, 30.0))


def test_stage_late_reply_does_not_shift_later_replies(bench):
    sim = bench.sim()
    stage = _stage(bench, sim)
    stage.move_to(5.0, 6.0, 30.0)
    # The first M114 is answered after the timeout (0.2 s), so it is sent again; the answer to
    # the second arrives 0.08 s after the first answer was accepted, i.e. after the host has
    # moved on. It must be drained, not read as the reply to the next command.
    sim.stage.inject("delay", match="M114", delay_s=0.35)
    sim.stage.inject("delay", match="M114", delay_s=0.08)
    assert stage.position() == pytest.approx((5.0, 6.0, 30.0))
    # The next move takes 0.1 s: its 'ok' must come after it is done, not be the late one.
    sim.stage.inject("busy", match="G0", delay_s=0.1)
    stage.command("G0 X7 Y8 Z31 F1200")
    assert sim.stage.position_mm == pytest.approx((7.0, 8.0, 31.0))
    assert stage.position() == pytest.approx((7.0, 8.0, 31.0))
    assert sim.stage.received.count("M114") == 3


def test_stage_persistent_timeout_names_port_and_command(bench):
    sim = bench.sim()
    stage = _stage(bench, sim)
    sim.stage.inject("drop", match="M114", times=3)
    with pytest.raises(RigTimeoutError) as err:
        stage.position()
    text = str(err.value)
    assert sim.stage_port in text and "'M114'" in text and "3 attempt(s)" in text
    assert "powered" in text
    assert sim.stage.received.count("M114") == 3


def test_stage_garbled_lines(bench):
    sim = bench.sim()
    stage = _stage(bench, sim)
    # Junk before a good reply: skipped, no re-send.
    sim.stage.inject("noise", match="G0", lines=2)
    stage.move_to(z_mm=33.0, rapid=True)
    assert sum(line.startswith("G0") for line in sim.stage.received) == 1
    # The 'ok' itself garbled: the command times out and is sent again.
    sim.stage.inject("garble", match="G0")
    stage.move_to(z_mm=34.0, rapid=True)
    assert sum(line.startswith("G0") for line in sim.stage.received) == 3
    # A garbled position line is an incomplete M114 reply: retried.
    sim.stage.inject("garble", match="M114")
    assert stage.position() == pytest.approx((0.0, 0.0, 34.0))
    assert sim.stage.received.count("M114") == 2


def test_stage_too_many_unexpected_lines(bench):
    sim = bench.sim()
    stage = _stage(bench, sim, max_unexpected_lines=2)
    sim.stage.inject("noise", match="M114", lines=3)
    with pytest.raises(StageError, match=r"3 unexpected lines while answering 'M114'"):
        stage.position()


def test_stage_error_reply_raises_and_does_not_move(bench):
    sim = bench.sim()
    stage = _stage(bench, sim)
    stage.move_to(20.0, 20.0, 30.0)
    sim.stage.inject("error", match="G1")
    with pytest.raises(StageError) as err:
        stage.move_to(21.0, 22.0, 29.0)
    assert "'G1 X21 Y22 Z29 F60'" in str(err.value)
    assert "'Error: simulated fault'" in str(err.value)
    assert sim.stage.position_mm == pytest.approx((20.0, 20.0, 30.0))
    assert stage.position() == pytest.approx((20.0, 20.0, 30.0))  # link still in step


def test_stage_busy_keepalive_extends_the_timeout(bench):
    sim = bench.sim()
    stage = _stage(bench, sim)
    sim.stage.inject("busy", match="M400", delay_s=0.6, busy_interval_s=0.05)  # > 0.4 s
    stage.move_to(1.0, 2.0, 3.0)
    assert sim.stage.received.count("M400") == 1


def test_stage_unknown_command(bench):
    sim = bench.sim()
    stage = _stage(bench, sim)
    with pytest.raises(StageError, match=r"does not know 'M999'"):
        stage.command("M999")


def test_soft_limits_refuse_before_sending(bench):
    sim = bench.sim()
    stage = _stage(bench, sim)
    sent = len(sim.stage.received)
    with pytest.raises(SoftLimitError) as err:
        stage.move_to(10.0, 10.0, -1.0)
    assert "Z=-1.0000 mm" in str(err.value) and "[0.0, 50.0]" in str(err.value)
    with pytest.raises(SoftLimitError, match=r"X=100\.5000 mm"):
        stage.move_to(x_mm=100.5)
    assert len(sim.stage.received) == sent


def test_lost_link_is_reported(bench):
    sim = bench.sim()
    stage = _stage(bench, sim)
    sim.stop()  # the device goes away while connected
    with pytest.raises(RigConnectionError) as err:
        stage.position()
    assert f"lost the link to the stage on '{sim.stage_port}'" in str(err.value)


def test_connection_errors(bench):
    stage = GCodeStage(StageConfig(port="/dev/no-such-stage-port"))
    with pytest.raises(RigConnectionError, match=r"'/dev/no-such-stage-port'.*list_ports"):
        stage.connect()
    assert not stage.is_connected
    with pytest.raises(RigConnectionError, match=r"not connected: call connect\(\)"):
        stage.position()


# -- gauge -----------------------------------------------------------------------------------


def _gauge(bench, sim, **overrides) -> ForceGauge:
    return bench.connect(ForceGauge(bench.config(sim, gauge=overrides).gauge))


def _put_tip(stage: GCodeStage, x_mm, y_mm, depth_mm):
    stage.move_to(*FRAME.sensor_to_stage(x_mm, y_mm, -depth_mm))


def test_gauge_tare_sign_and_units(bench):
    # A gauge that reports compression as negative kgf with a 0.8 N zero offset.
    sim = bench.sim(
        offset_n=0.8, sign=-1, newtons_per_unit=9.80665, reply_format="F={value:+.5f} kgf"
    )
    stage = _stage(bench, sim)
    gauge = _gauge(
        bench, sim, reply_regex=r"F=(?P<value>[-+]\d+\.\d+) kgf", force_sign=-1,
        newtons_per_unit=9.80665,
    )
    _put_tip(stage, 2.0, 1.0, -1.0)  # 1 mm above the gel
    assert gauge.tare() == pytest.approx(0.8, abs=1e-3)
    _put_tip(stage, 2.0, 1.0, 1.2)
    assert gauge.read_n() == pytest.approx(planted_force(1.2, 2.0, 1.0), abs=1e-3)
    assert gauge.read_n(samples=3) == pytest.approx(planted_force(1.2, 2.0, 1.0), abs=1e-3)


def test_gauge_garbled_reply_is_requested_again(bench):
    sim = bench.sim()
    stage = _stage(bench, sim)
    gauge = _gauge(bench, sim)
    _put_tip(stage, 0.0, 0.0, 0.9)
    sim.gauge.inject("garble")
    n_before = sim.gauge.received.count("?")
    assert gauge.read_raw_n() == pytest.approx(planted_force(0.9, 0.0, 0.0), abs=0.006)
    assert sim.gauge.received.count("?") - n_before == 2


def test_gauge_too_many_garbled_replies(bench):
    sim = bench.sim()
    gauge = _gauge(bench, sim, max_unexpected_lines=1)
    sim.gauge.inject("garble", times=2)
    with pytest.raises(GaugeError, match=r"2 replies to '\?' that do not match reply_regex"):
        gauge.read_n()


def test_gauge_timeouts(bench):
    sim = bench.sim()
    stage = _stage(bench, sim)
    gauge = _gauge(bench, sim)
    _put_tip(stage, 0.0, 0.0, 0.5)
    sim.gauge.inject("drop")
    assert gauge.read_raw_n() == pytest.approx(planted_force(0.5, 0.0, 0.0), abs=0.006)
    # Late replies (0.35 s > timeout 0.2 s, then 0.08 s after the host moved on) must not be
    # read as the next reading.
    sim.gauge.inject("delay", delay_s=0.35)
    sim.gauge.inject("delay", delay_s=0.08)
    assert gauge.read_raw_n() == pytest.approx(planted_force(0.5, 0.0, 0.0), abs=0.006)
    _put_tip(stage, 0.0, 0.0, 1.5)
    assert gauge.read_raw_n() == pytest.approx(planted_force(1.5, 0.0, 0.0), abs=0.006)
    sim.gauge.inject("drop", times=3)
    with pytest.raises(RigTimeoutError) as err:
        gauge.read_n()
    assert sim.gauge_port in str(err.value) and "'?'" in str(err.value)
    assert "3 attempt(s)" in str(err.value)


# -- presses ---------------------------------------------------------------------------------


def test_press_sequence_records_match_force_fn(bench):
    sim = bench.sim(offset_n=0.37)  # the per-press tare must remove it
    rig = bench.connect(IndentationRig(bench.config(sim)))
    rig.home()
    contacts = [(0.0, 0.0, 1.0), (3.0, -2.0, 0.6), (-4.0, 2.5, 1.4)]
    seen = []

    def on_pressed(record):
        seen.append((sim.contact(), sim.force_n(), record))

    records = rig.press_sequence(contacts, on_pressed=on_pressed)
    assert len(records) == len(seen) == 3
    for (x, y, d), record, (contact, true_force, passed) in zip(contacts, records, seen):
        assert passed is record
        assert contact == pytest.approx((x, y, d), abs=1e-6)
        assert true_force == pytest.approx(planted_force(d, x, y))
        assert record.force_n == pytest.approx(planted_force(d, x, y), abs=0.011)
        assert not record.force_limited and record.reached_depth_mm == pytest.approx(d)
        # X runs against x in FRAME: 42 - x.
        assert record.stage_target_mm == pytest.approx((42.0 - x, 37.5 + y, 18.0 - d))
        assert record.stage_readback_mm == pytest.approx(record.stage_target_mm, abs=0.006)
        assert record.tip_readback_mm == pytest.approx((x, y, -d), abs=0.006)
    assert [r.timestamp_s for r in records] == sorted(r.timestamp_s for r in records)
    assert sim.contact().depth_mm == 0.0
    assert sim.stage.position_mm[2] == pytest.approx(18.0 + 5.0)  # travel height


def test_press_on_a_domed_surface(bench):
    def surface(x, y):
        return -0.02 * (x * x + y * y)

    def dome_force(indentation, x, y):  # indentation counted from the curved surface
        return planted_force(indentation + surface(x, y), x, y)

    sim = bench.sim(force_fn=dome_force)
    rig = bench.connect(IndentationRig(bench.config(sim)))
    records = rig.press_sequence([(4.0, 3.0, 0.8)], surface_z_fn=surface)
    # surface at (4, 3) is -0.5 mm: tip at z = -1.3
    assert records[0].tip_readback_mm == pytest.approx((4.0, 3.0, -1.3), abs=0.006)
    assert records[0].force_n == pytest.approx(planted_force(0.8, 4.0, 3.0), abs=0.011)


def test_press_steps_and_averaging(bench):
    sim = bench.sim(noise_std_n=0.02, seed=3)
    rig = bench.connect(
        IndentationRig(bench.config(sim, approach_step_mm=0.05, force_samples=4, dwell_s=0.02))
    )
    requests_before = sim.gauge.received.count("?")
    history_before = len(sim.stage.history_mm)
    record = rig.press(1.0, 2.0, 0.63)
    # 1 mm clearance + 0.63 mm depth in steps of at most 0.05 mm: ceil(32.6) = 33 steps
    z_steps = [p[2] for p in sim.stage.history_mm[history_before:]]
    start = z_steps.index(18.0 + 1.0)
    pressing = z_steps[start:start + 34]
    assert len(pressing) == 34 and pressing[-1] == pytest.approx(18.0 - 0.63)
    assert all(0 < a - b <= 0.05 + 1e-9 for a, b in zip(pressing, pressing[1:]))
    # readings: 2 for the tare, 1 at the approach start, 1 per step, 4 averaged at full depth
    assert sim.gauge.received.count("?") - requests_before == 2 + 1 + 33 + 4
    assert record.force_n == pytest.approx(planted_force(0.63, 1.0, 2.0), abs=0.011 + 0.04)


def test_force_limit_stops_and_backs_off(bench):
    sim = bench.sim()
    limit_n, step_mm = 1.0, 0.05
    rig = bench.connect(
        IndentationRig(bench.config(sim, force_limit_n=limit_n, approach_step_mm=step_mm))
    )
    called = []
    record = rig.press(0.0, 0.0, 2.0, on_pressed=called.append)
    # planted_force at x = y = 0 reaches 1 N at d* = (1 / K)^(2/3)
    d_star = (limit_n / K_N_PER_MM1P5) ** (2.0 / 3.0)
    assert record.force_limited and called == []
    assert d_star <= record.reached_depth_mm <= d_star + step_mm + 1e-9
    assert limit_n < record.force_n <= planted_force(d_star + step_mm, 0, 0) + 0.006
    depths = [-FRAME.stage_to_sensor(*p)[2] for p in sim.stage.history_mm]
    deepest = max(range(len(depths)), key=depths.__getitem__)
    assert depths[deepest] == pytest.approx(record.reached_depth_mm)
    assert depths[deepest] <= d_star + step_mm + 1e-9
    assert all(d < depths[deepest] for d in depths[deepest + 1:])
    assert sim.contact().depth_mm == 0.0  # backed off
    assert sim.stage.position_mm[2] == pytest.approx(18.0 + 5.0)


def test_press_refuses_unreachable_contacts_before_moving(bench):
    sim = bench.sim()
    rig = bench.connect(IndentationRig(bench.config(sim)))
    sent = len(sim.stage.received)
    with pytest.raises(SoftLimitError, match=r"Z=-2\.0000 mm"):  # 18 - 20
        rig.press_sequence([(0.0, 0.0, 1.0), (0.0, 0.0, 20.0)])
    with pytest.raises(ValueError, match=r"contact 0 is \(1\.0, 2\.0\)"):
        rig.press_sequence([(1.0, 2.0)])
    assert len(sim.stage.received) == sent


def test_press_retracts_when_the_stage_fails(bench):
    sim = bench.sim()
    rig = bench.connect(IndentationRig(bench.config(sim)))
    sim.stage.inject("error", match="G1 Z")  # the first approach step
    with pytest.raises(StageError, match=r"rejected 'G1 Z"):
        rig.press(1.0, 1.0, 1.0)
    assert sim.stage.position_mm[2] == pytest.approx(18.0 + 5.0)
    reading = rig.read()
    assert reading.stage_mm == pytest.approx((41.0, 38.5, 23.0))
    assert reading.force_n == pytest.approx(0.0, abs=0.006)


# -- command line ----------------------------------------------------------------------------


def test_cli_press_prints_the_force(bench, tmp_path):
    sim = bench.sim(force_fn=HertzForce(1.9), frame=StageFrame())  # the CLI's default frame
    runner = CliRunner()
    args = ["press", "--stage", sim.stage_port, "--gauge", sim.gauge_port,
            "--x-mm", "1", "--y-mm", "-2", "--depth-mm", "0.8"]
    result = runner.invoke(rig_app, args)
    assert result.exit_code == 0, result.output
    force = float(result.stdout.split("force ")[1].split(" N")[0])
    assert force == pytest.approx(1.9 * 0.8**1.5, abs=0.006)
    assert "stage read-back X=51.000 Y=48.000 Z=19.200 mm" in result.stdout

    config_path = tmp_path / "rig.json"
    save_rig_config(sim.rig_config(force_limit_n=0.5), config_path)
    result = runner.invoke(rig_app, ["press", "--config", str(config_path), "--x-mm", "0",
                                     "--y-mm", "0", "--depth-mm", "0.8", "--json"])
    assert result.exit_code == EXIT_FORCE_LIMITED, result.output
    assert json.loads(result.stdout)["force_limited"] is True

    result = runner.invoke(rig_app, ["press", "--stage", "/dev/no-such-port", "--gauge",
                                     sim.gauge_port, "--x-mm", "0", "--y-mm", "0",
                                     "--depth-mm", "1"])
    assert result.exit_code == 1 and "/dev/no-such-port" in result.stderr


def test_cli_simulate_writes_a_usable_config(bench, tmp_path):
    config_path = tmp_path / "sim.json"
    result = CliRunner().invoke(
        rig_app, ["simulate", "--duration-s", "0.05", "--write-config", str(config_path)]
    )
    assert result.exit_code == 0, result.output
    cfg = load_rig_config(config_path)
    assert f"stage port: {cfg.stage.port}" in result.stdout
    assert f"gauge port: {cfg.gauge.port}" in result.stdout
    assert cfg.stage.port != cfg.gauge.port and cfg.stage.frame == StageFrame()
