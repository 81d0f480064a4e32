"""Capture sessions: the safety envelope, the plan, and sessions on the virtual rig, with
faults injected in the twins (over real ptys and pyserial) and a process killed mid-run."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from rig import plan as P
from rig.envelope import CLEARANCE_M, EnvelopeError, SafetyEnvelope
from rig.twins.printer import TwinFaults
from scenes.dataset import read_samples
from scenes.kinematics import RigLayout, head_for_tap, sensor_to_world
from scenes.protocol import base_protocol
from scenes.renderers import get_renderer

#: The drivers' reply timeout against the twins, seconds.
REPLY_TIMEOUT_S = 0.4
#: M114 reports 0.01 mm; the servo board 0.01 degree.
POSITION_RESOLUTION_M = 0.01e-3
ANGLE_RESOLUTION_RAD = math.radians(0.01)


@pytest.fixture(scope="module")
def vertices():
    from scenes.indenters import indenter

    return {name: np.asarray(indenter(name).vertices) for name in ("sphere", "cone")}


@pytest.fixture(scope="module")
def envelope(spec, mesh, vertices):
    return SafetyEnvelope.for_sensor(spec, mesh, vertices)


@pytest.fixture(scope="module")
def protocol(spec, mesh):
    return base_protocol(spec, mesh, ("sphere", "cone"))


def _head(tap, vertices, layout=RigLayout()):
    return head_for_tap(tap, vertices[tap.object], layout)


# --------------------------------------------------------------------------- envelope


def test_the_envelope_measures_a_press_as_deep_as_the_tap(envelope, protocol, vertices):
    for tap in protocol.taps:
        depth = envelope.indentation(tap.object, _head(tap, vertices), tap.indenter_pitch, tap.sensor_roll)
        if tap.object == "sphere":
            # The sphere's deepest point lies on the normal line: its press is the tap's depth.
            assert depth == pytest.approx(tap.depth, abs=2e-5), tap
        else:
            # A cone's tip may lie off the contact point, where the membrane curves away.
            assert tap.depth - 0.5e-3 < depth < tap.depth + 2e-5, tap


def test_the_envelope_refuses_what_would_do_harm(envelope, protocol, vertices):
    tap = protocol.taps[4]  # the apex... (row 0, position 4: a cylinder tap from above)
    head = _head(tap, vertices)
    n = sensor_to_world(tap.sensor_roll) @ np.asarray(tap.normal)
    args = (tap.indenter_pitch, tap.sensor_roll)
    assert envelope.check_pose("sphere", head, *args, "press", press=True) == pytest.approx(tap.depth, abs=2e-5)
    with pytest.raises(EnvelopeError, match="deeper than the safe 2.500 mm"):
        envelope.check_pose("sphere", head - 0.001 * n, *args, "too deep", press=True)
    with pytest.raises(EnvelopeError, match="not a press"):
        envelope.check_pose("sphere", head, *args, "a travel move")
    # Just clear of the membrane is not clear enough for a travel move; further out is.
    with pytest.raises(EnvelopeError, match="from the membrane on a move that is not a press"):
        envelope.check_pose("sphere", head + (tap.depth + 0.5 * CLEARANCE_M) * n, *args, "close")
    envelope.check_pose("sphere", head + (tap.depth + 2 * CLEARANCE_M) * n, *args, "clear")
    with pytest.raises(EnvelopeError, match=r"outside the build volume \[0.0850, 0.4000\]"):
        envelope.check_head([0.1, 0.0, 0.5], "too high")
    with pytest.raises(EnvelopeError, match="below the bed"):
        low = SafetyEnvelope(RigLayout(travel_z=(-0.1, 0.4)), envelope.membrane, envelope.indenters, 0.0025)
        low.check_pose("sphere", [0.0, 0.1, 0.0], 0.0, 0.0, "low")
    with pytest.raises(EnvelopeError, match="not in the envelope"):
        envelope.check_pose("teapot", head, *args, "teapot")
    # A press that starts inside the sensor is refused along its path, not just at its end.
    with pytest.raises(EnvelopeError, match="deeper than the safe"):
        envelope.check_move("sphere", head - 0.004 * n, head, *args, "through", press=True)


# --------------------------------------------------------------------------- plan


def test_the_plan_turns_servos_only_at_the_safe_height_and_presses_along_the_normal(protocol, vertices, envelope):
    layout = RigLayout()
    steps = P.plan(protocol.taps, vertices, layout, envelope)
    head, safe_z = None, layout.home[2]
    presses = 0
    for i, step in enumerate(steps):
        if step.kind == P.SERVOS:
            assert head is not None and head[2] == pytest.approx(safe_z)
            assert steps[i - 1].kind == P.WAIT  # the head has arrived before the servos turn
        if step.kind == P.MOVE:
            if step.press and steps[i + 1].kind == P.WAIT:
                tap = protocol.taps[step.tap]
                n = sensor_to_world(tap.sensor_roll) @ np.asarray(tap.normal)
                travel = np.asarray(step.head) - head
                assert np.allclose(travel, -(P.APPROACH_M + tap.depth) * n, atol=1e-12)
                assert step.feed == P.PRESS_FEED_M_S
                presses += 1
            head = np.asarray(step.head)
        if step.kind == P.CAPTURE and step.tap is not None:
            assert steps[i - 1].kind == P.WAIT  # M400 before each capture
    assert presses == len(protocol.taps)
    assert [s.obj for s in steps if s.kind == P.MOUNT] == ["sphere", "cone"]
    stream = [line for step in steps for line in P.device_lines(step, layout)]
    assert stream[0] == ("printer", "G28")
    assert sum(device == "camera" for device, _ in stream) == len(protocol.taps) + 1


def test_a_protocol_out_of_reach_or_of_servo_range_is_refused_before_any_port(spec, protocol, tmp_path):
    from rig.session import prepare

    with pytest.raises(EnvelopeError, match=r"tap 0 \(sphere\).*outside the build volume"):
        prepare(tmp_path / "a", spec, protocol, RigLayout(travel_x=(-0.05, 0.2)))
    # Roll 2 pi further is the same pose for the protocol, but beyond the roll servo's travel:
    # the protocol's own check (scenes.protocol_checks.validate) refuses it by name.
    taps = list(protocol.taps[:18])
    taps[12] = replace(taps[12], sensor_roll=taps[12].sensor_roll + 2 * math.pi)
    with pytest.raises(ValueError, match=r"tap 12 \(object 'sphere'.*the rig cannot reach it: sensor_roll 9.425"):
        prepare(tmp_path / "b", spec, replace(protocol, taps=tuple(taps)))
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_dry_run_prints_the_stream_and_opens_nothing(tmp_path, capsys):
    from scenes.cli import main

    code = main(["rig", "run", "--printer", "/dev/does-not-exist", "--servos", "/dev/nor-this", "--camera", "7",
                 "--objects", "sphere", "--out", str(tmp_path / "d"), "--dry-run"])
    out = capsys.readouterr()
    assert code == 0
    lines = out.out.splitlines()
    assert lines[0] == "printer: G28" and "servos: S R 0.00*31" in lines
    assert sum(line.startswith("camera: capture tap") for line in lines) == 18
    assert "nothing was sent" in out.err and not (tmp_path / "d").exists()
    code = main(["rig", "run", "--printer", "twin", "--servos", "twin", "--camera", "twin", "--objects", "sphere",
                 "--layout", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "e"), "--dry-run"])
    assert code == 1 and "--layout" in capsys.readouterr().err
    # a twin's unit is for the twin only, and its settings are numbers
    for unit, message in [("membrane_compliance=1.2", "--unit is for --camera twin only"),
                          ("membrane_compliance", "expected NAME=VALUE"), ("led_peak_shift=a,b", "expected NAME=VALUE")]:
        assert main(["rig", "run", "--objects", "sphere", "--unit", unit, "--out", str(tmp_path / "f"),
                     "--dry-run"]) == 1
        assert message in capsys.readouterr().err
    assert not (tmp_path / "f").exists()


def test_dry_run_needs_no_devices_and_a_real_run_names_those_it_lacks(tmp_path, capsys):
    from scenes.cli import main

    with_ports = ["--printer", "/dev/does-not-exist", "--servos", "/dev/nor-this", "--camera", "7"]
    assert main(["rig", "run", *with_ports, "--objects", "sphere", "--limit", "2", "--out", str(tmp_path / "d"),
                 "--dry-run"]) == 0
    expected = capsys.readouterr().out
    assert expected.startswith("printer: G28\n")
    assert main(["rig", "run", "--objects", "sphere", "--limit", "2", "--out", str(tmp_path / "d"), "--dry-run"]) == 0
    assert capsys.readouterr().out == expected
    with pytest.raises(SystemExit) as exit_info:
        main(["rig", "run", "--servos", "/dev/nor-this", "--objects", "sphere", "--out", str(tmp_path / "d")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.splitlines()[-1] == ("tactile-sim rig run: error: the following arguments are required without "
                                    "--dry-run: --printer, --camera")
    assert not (tmp_path / "d").exists()


# --------------------------------------------------------------------------- sessions


def _needs_virtual_rig():
    """Skip, saying why, where the MuJoCo rig cannot be built (no GL context, no MuJoCo)."""
    from scenes.gl import GLPlatformError, choose_gl

    try:
        choose_gl()
    except GLPlatformError as exc:
        pytest.skip(str(exc))
    pytest.importorskip("mujoco", reason="MuJoCo is not installed (pip install '.[mujoco]')")


@pytest.fixture
def virtual(spec):
    """Make a virtual rig (twins with faults) and drivers connected to it."""
    _needs_virtual_rig()
    from rig.marlin import MarlinPrinter
    from rig.servos import ServoBoard
    from rig.session import Devices
    from rig.virtual import VirtualRig

    opened = []

    def make(objects=("sphere",), printer_faults=None, servo_faults=None, camera=None):
        rig = VirtualRig(spec, objects, get_renderer("phong"), {}, printer_faults=printer_faults,
                         servo_faults=servo_faults)
        opened.append(rig)
        printer = MarlinPrinter(rig.printer.port, reply_timeout_s=REPLY_TIMEOUT_S)
        servos = ServoBoard(rig.servos.port, reply_timeout_s=REPLY_TIMEOUT_S)
        opened.extend([printer, servos])
        return rig, Devices(printer, servos, camera or rig.camera, rig.mount, 0.0)

    yield make
    for thing in reversed(opened):
        thing.close()


def _eventually(condition, seconds: float = 2.0) -> bool:
    """Whether ``condition()`` holds within ``seconds`` (the twin's thread acts on a line
    after the host has written it)."""
    deadline = time.monotonic() + seconds
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def _taps(protocol, n):
    return replace(protocol, taps=protocol.taps[:n])


def _check_dataset(root: Path, protocol):
    records = read_samples(root)
    ids = [r["id"] for r in records]
    assert len(ids) == len(set(ids)), "a sample was recorded twice"
    for r in records:
        assert (root / r["image"]).exists()
    return records


def test_a_virtual_session_captures_what_the_dataset_generator_renders(spec, protocol, virtual, tmp_path):
    from rig.session import prepare
    from scenes.generate import Job, no_contact, runner
    from scenes.images import read_rgb

    short = _taps(protocol, 4)
    rig, devices = virtual()
    session = prepare(tmp_path / "cap", spec, short, source_meta={"rig": {"virtual": True}})
    session.hidden = rig.hidden()
    summary = session.run(devices, progress=False)
    assert summary["new"] == 4
    records = _check_dataset(tmp_path / "cap", short)
    meta = json.loads((tmp_path / "cap" / "dataset.json").read_text())
    assert meta["source"] == "real" and meta["rig"]["virtual"] is True
    assert "phong" not in json.dumps(meta)  # the hidden settings are elsewhere
    assert json.loads((tmp_path / "cap" / "virtual.json").read_text())["renderer"] == "phong"
    job = Job(spec, get_renderer("phong").make_renderer, {}, ("sphere",))
    for record, tap in zip(records, short.taps):
        for joint, value in record["commanded_pose"].items():
            tolerance = POSITION_RESOLUTION_M if joint.startswith("printer") else ANGLE_RESOLUTION_RAD
            assert abs(record["measured_pose"][joint] - value) <= tolerance, joint
        assert record["measured_depth"] == pytest.approx(tap.depth, abs=POSITION_RESOLUTION_M)
        expected = runner(job).run(tap)["image"]
        got = read_rgb(tmp_path / "cap" / record["image"])
        assert np.abs(got - expected).mean() < 1.0 / 255, record["id"]
    background = read_rgb(tmp_path / "cap" / "background.png")
    assert np.abs(background - no_contact(job)).mean() < 1.0 / 255


def test_lost_and_corrupted_lines_are_resent_and_no_move_runs_twice(spec, protocol, virtual, tmp_path):
    from rig.session import prepare

    short = _taps(protocol, 3)
    # N4 and N11 are moves, N8 an M400 and N14 the first tap's M114; 10 % of all lines fail
    # their checksum.
    faults = TwinFaults(drop_lines=frozenset({4, 11}), corrupt_lines=frozenset({8, 14}), corrupt_rate=0.1, seed=3)
    rig, devices = virtual(printer_faults=faults)
    session = prepare(tmp_path / "cap", spec, short)
    moves = sum(step.kind == P.MOVE for step in session.steps)
    session.run(devices, progress=False)
    assert len(_check_dataset(tmp_path / "cap", short)) == 3
    assert rig.printer.rejected and rig.printer.dropped  # the faults did happen
    assert len(rig.printer.moves) == moves


def test_a_printer_error_stops_the_machine_and_the_session_resumes(spec, protocol, virtual, tmp_path):
    from rig.session import SessionAborted, prepare

    short = _taps(protocol, 5)
    # N3 is G28; each tap after the first takes 8 lines or so: fail in the third tap.
    rig, devices = virtual(printer_faults=TwinFaults(error_at_line=30, error_text="MINTEMP triggered"))
    with pytest.raises(SessionAborted, match="MINTEMP.*M112.*run the same command again to resume"):
        prepare(tmp_path / "cap", spec, short).run(devices, progress=False)
    assert _eventually(lambda: rig.printer.halted)
    first = _check_dataset(tmp_path / "cap", short)
    assert 0 < len(first) < 5
    rig2, devices2 = virtual()
    session = prepare(tmp_path / "cap", spec, short)
    assert len(session.todo) == 5 - len(first)
    session.run(devices2, progress=False)
    records = _check_dataset(tmp_path / "cap", short)
    assert [r["tap_index"] for r in records] == list(range(5))


def test_a_silent_printer_times_out_and_gets_the_emergency_stop(spec, protocol, virtual, tmp_path):
    from rig.session import SessionAborted, prepare

    rig, devices = virtual(printer_faults=TwinFaults(silent_from_line=12))
    with pytest.raises(SessionAborted, match="PrinterTimeout.*M112"):
        prepare(tmp_path / "cap", spec, _taps(protocol, 2)).run(devices, progress=False)
    assert _eventually(lambda: rig.printer.halted)
    assert [text for _, text in rig.printer.lines][-1] == "M112"


def test_a_disconnect_mid_run_stops_and_the_session_resumes(spec, protocol, virtual, tmp_path):
    from rig.session import SessionAborted, prepare

    short = _taps(protocol, 4)
    rig, devices = virtual()
    moves = []

    def unplug(position):  # the cable comes out during the third tap
        rig._on_move(position)
        moves.append(position)
        if len(moves) == 14:
            rig.printer.unplug()

    rig.printer.on_move = unplug
    with pytest.raises(SessionAborted, match="PrinterError"):
        prepare(tmp_path / "cap", spec, short).run(devices, progress=False)
    first = len(_check_dataset(tmp_path / "cap", short))
    assert 0 < first < 4
    rig2, devices2 = virtual()
    prepare(tmp_path / "cap", spec, short).run(devices2, progress=False)
    assert [r["tap_index"] for r in _check_dataset(tmp_path / "cap", short)] == list(range(4))


def test_ctrl_c_quick_stops_and_retracts_the_indenter(spec, protocol, virtual, tmp_path):
    from rig.session import SessionAborted, prepare

    class Interrupted:
        def __init__(self, camera):
            self.camera, self.grabs = camera, 0

        def settle(self):
            pass

        def describe(self):
            return self.camera.describe()

        def grab(self):
            self.grabs += 1
            if self.grabs == 3:  # the background, tap 0, then Ctrl-C pressing tap 1
                raise KeyboardInterrupt
            return self.camera.grab()

    rig, devices = virtual()
    devices.camera = Interrupted(rig.camera)
    short = _taps(protocol, 3)
    with pytest.raises(SessionAborted, match="interrupted.*M410.*retracted"):
        prepare(tmp_path / "cap", spec, short).run(devices, progress=False)
    commands = [text for _, text in rig.printer.lines]
    stop = max(i for i, text in enumerate(commands) if text.startswith("M410"))
    assert any(text.startswith("G1") for text in commands[stop:])  # backed out after the stop
    assert not rig.printer.halted
    head = RigLayout().head_position(rig.printer.position_m)
    assert head[2] == pytest.approx(RigLayout().home[2], abs=POSITION_RESOLUTION_M)
    assert len(_check_dataset(tmp_path / "cap", short)) == 1


@pytest.mark.slow
def test_killing_the_process_mid_run_loses_and_duplicates_nothing(tmp_path):
    pytest.importorskip("mujoco", reason="MuJoCo is not installed (pip install '.[mujoco]')")
    out = tmp_path / "cap"
    command = [sys.executable, "-m", "scenes.cli", "rig", "run", "--printer", "twin", "--servos", "twin",
               "--camera", "twin", "--objects", "sphere", "--limit", "8", "--no-alignment", "--quiet",
               "--out", str(out)]
    proc = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    deadline = time.monotonic() + 120
    samples = out / "samples.jsonl"
    while time.monotonic() < deadline and proc.poll() is None:
        if samples.exists() and len(samples.read_text().splitlines()) >= 3:
            os.killpg(proc.pid, signal.SIGKILL)
            break
        time.sleep(0.02)
    proc.wait(30)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.read().decode()[-2000:]
    before = len(read_samples(out, repair=True))
    assert 3 <= before < 8
    done = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    records = read_samples(out)
    assert [r["tap_index"] for r in records] == list(range(8))
    assert f"8 samples in {out} ({8 - before} new" in done.stdout
    # the fast path's twin has no exposure of its own (the reference's sets it: "auto")
    assert json.loads((out / "dataset.json").read_text())["renderer"]["camera"]["exposure"] == "fixed"


@pytest.mark.parametrize("renderer, options, exposure", [("pbr", {}, "auto"), ("pbr", {"profile": "unit.toml"}, "fixed"),
                                                         ("phong", {}, "fixed")])
def test_the_twin_camera_says_who_sets_its_exposure(spec, renderer, options, exposure):
    """The reference's own rule sets a capture's exposure ("auto": the diagnosis fits it);
    with a profile, the unit's gains and response set the image instead."""
    _needs_virtual_rig()
    from rig.virtual import VirtualRig

    with VirtualRig(spec, ("sphere",), get_renderer(renderer), options) as rig:
        assert rig.camera.describe()["exposure"] == exposure


def test_a_twin_unit_is_refused_where_it_cannot_be_built(spec):
    from rig.virtual import unit_spec

    unit, compliance = unit_spec(spec, {"membrane_compliance": 1.3, "layer_spread": 0.3, "led_peak_shift": (5, -5, 0)})
    assert compliance == 1.3 and unit.elastic.poisson_ratio == 0.3 and spec.elastic.poisson_ratio == 0.5
    assert [b.peak_nm - a.peak_nm for a, b in zip(spec.leds, unit.leds)] == [5, -5, 0]
    assert [b.peak_nm - a.peak_nm for a, b in zip(spec.leds, unit_spec(spec, {"led_peak_shift": 4})[0].leds)] == [4] * 3
    assert unit_spec(spec, {}) == (spec, 1.0)
    assert unit_spec(spec, {"led_power": (1.2, 0.8, 1.0)}) == (spec, 1.0)  # the renderer's, not the spec's
    for bad, message in [({"compliance": 1.2}, "not one the twin can change.*membrane_compliance"),
                         ({"membrane_compliance": 5.0}, r"membrane_compliance must be one number in \[0.3, 2\]"),
                         ({"layer_spread": 0.7}, "a Poisson ratio"), ({"led_peak_shift": (1, 2)}, "1 or 3 shifts"),
                         ({"layer_spread": float("nan")}, "must be finite numbers"),
                         ({"camera_gains": (1.0, 1.1)}, r"camera_gains is .* \(R, G, B\).*got \(1.0, 1.1\)"),
                         ({"camera_gains": (1.0, 1.1, 9.0)}, "each in \\[0.25, 4\\]"),
                         ({"alignment": (1.0, 2.0, 0.5)}, r"\|turn\| <= 0.2"), ({"blur": -1.0}, "defocus"),
                         ({"led_power": (1.0, 2.0)}, r"led_power must be 1 or 3 powers in \[0.25, 4\]"),
                         ({"led_power": 9.0}, r"led_power must be 1 or 3 powers in \[0.25, 4\], got \(9.0,\)")]:
        with pytest.raises(ValueError, match=message):
            unit_spec(spec, bad)


def test_a_twin_units_led_powers_go_to_the_reference_and_only_there(spec):
    """The reference renders each LED's power (pbr option led_power); the fast path's LEDs
    have only colours, so the phong twin refuses the entry before building anything."""
    from rig.virtual import VirtualRig

    with pytest.raises(ValueError, match="unit led_power needs the pbr camera twin"):
        VirtualRig(spec, ("sphere",), get_renderer("phong"), {}, unit={"led_power": (1.2, 0.8, 1.0)})
    _needs_virtual_rig()
    with VirtualRig(spec, ("sphere",), get_renderer("pbr"), {"film": [80, 60]}, unit={"led_power": 1.5}) as rig:
        assert rig.options == {"film": [80, 60], "led_power": [1.5, 1.5, 1.5]}  # one for every LED
        assert rig.unit_spec == spec


def test_a_twin_units_camera_blurs_moves_and_balances_the_image_as_a_camera_would():
    """The unit's own camera on a rendered image: a defocus disc of the stated radius that
    keeps the light, a rigid motion that carries a point where the turn and shift put it,
    and per-channel gains, clipped."""
    from rig.virtual import unit_image

    image = np.zeros((41, 61, 3), np.float32)
    image[20, 40] = 1.0  # 10 px right of the centre (row 20, col 30)
    blurred = unit_image(image, {"blur": 2.5})
    rows, cols = np.nonzero(blurred[..., 0] > 0)
    assert blurred[..., 0].sum() == pytest.approx(1.0, abs=1e-6)
    assert np.hypot(rows - 20, cols - 40).max() <= 2.5 + 0.75 and np.hypot(rows - 20, cols - 40).max() >= 2.5 - 0.75
    assert np.ptp(blurred[20, 39:42, 0]) < 1e-6  # a disc is flat inside, unlike a Gaussian
    turn = 0.2
    moved = unit_image(image, {"alignment": (3.0, -2.0, turn)})
    row, col = np.unravel_index(np.argmax(moved[..., 0]), moved.shape[:2])
    assert (row, col) == (round(20 - 2.0 + 10 * np.sin(turn)), round(30 + 3.0 + 10 * np.cos(turn)))
    balanced = unit_image(np.full((4, 4, 3), 0.5, np.float32), {"camera_gains": (1.2, 1.0, 2.5)})
    np.testing.assert_allclose(balanced[0, 0], [0.6, 0.5, 1.0])
    assert unit_image(image, {"membrane_compliance": 1.2}) is image  # no camera entry: the image as it is


def test_a_twin_unit_presses_deeper_and_renders_its_own_spec(spec, monkeypatch):
    """The twin's unit is what it renders: its compliance scales the imprint it renders,
    its elastomer is the renderer's, its camera takes the image, and virtual.json names it;
    the capture records the spec."""
    _needs_virtual_rig()
    import scenes.generate
    from rig.virtual import VirtualRig

    seen = []
    monkeypatch.setattr(scenes.generate, "render_sample", lambda renderer, depth: seen.append(depth) or
                        {"image": np.full((*depth.shape, 3), 0.4, np.float32)})
    unit = {"membrane_compliance": 1.5, "layer_spread": 0.25, "camera_gains": (2.0, 1.0, 0.5)}
    with VirtualRig(spec, ("sphere",), get_renderer("phong"), {}, unit=unit) as rig:
        rig.renderer()
        ref = np.asarray(rig.ref_depth, np.float32)
        pressed = ref.copy()
        pressed[200:260, 300:340] -= 1e-3
        rig.rig.depth = lambda: pressed
        image = rig.camera.grab()
        np.testing.assert_allclose(seen[-1], ref - 1.5 * (ref - pressed), atol=1e-6)
        np.testing.assert_allclose(image[0, 0], [0.8, 0.4, 0.2], rtol=1e-6)  # through the unit's own camera
        assert rig.unit_spec.elastic.poisson_ratio == 0.25 and rig.spec == spec
        assert rig.hidden()["unit"] == unit


def test_a_background_that_cannot_be_registered_is_recorded_not_fatal(spec, capsys):
    from rig.cli import _alignment_hook

    extra = _alignment_hook(spec, {})(np.zeros((480, 640, 3), np.float32))  # a black frame
    assert set(extra) == {"alignment_error"} and "black or saturated" in extra["alignment_error"]
    assert "warning: no alignment" in capsys.readouterr().err


def test_rig_twin_serves_both_twins_and_prints_their_ports(capsys):
    from scenes.cli import main

    assert main(["rig", "twin", "--seconds", "0.2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split(": ")[0] for line in lines] == ["printer twin", "servo twin"]
    assert all(line.split(": ")[1].startswith("/dev/pts/") for line in lines)
