"""The servo board: its protocol's pure functions (worked by hand first), the driver against
its twin on a real pty with real pyserial, and the Arduino sketch (its constants agree with
Python's; it compiles for the Mega when arduino-mk and avr-gcc are installed)."""

from __future__ import annotations

import math
import re
import shutil
import subprocess
import time
from pathlib import Path

import pytest

pytest.importorskip("serial", reason="pyserial is not installed (pip install '.[rig]')")

from rig import servo_protocol as sp
from rig.servos import ServoBoard, ServoError, ServoTimeout
from rig.twins.servos import DEFAULT_OFFSETS_CENTIDEG, ServoFaults, ServoTwin

SKETCH_DIR = Path(__file__).resolve().parents[1] / "rig" / "firmware" / "servo_rig"
#: Reply timeout for the twin, seconds: it answers in well under a millisecond.
TWIN_REPLY_TIMEOUT_S = 0.3
TWIN_BANNER_TIMEOUT_S = 1.0
#: The wire carries 0.01 degree.
WIRE_RESOLUTION_RAD = math.radians(0.01)
#: Arrival numbers after connecting: H is 0, set_angles writes roll at 1 and pitch at 2.
ROLL_LINE, PITCH_LINE = 1, 2
ROLL_RAD, PITCH_RAD = math.pi / 2, math.radians(30.0)


@pytest.fixture
def session():
    """Make a twin with faults and a connected board; close both afterwards."""
    opened = []

    def make(faults: ServoFaults | None = None, **kwargs):
        twin = ServoTwin(faults, **kwargs)
        opened.append(twin)
        board = ServoBoard(twin.port, reply_timeout_s=TWIN_REPLY_TIMEOUT_S, banner_timeout_s=TWIN_BANNER_TIMEOUT_S)
        opened.append(board)
        return twin, board

    yield make
    for thing in reversed(opened):
        thing.close()


# ---------------------------------------------------------------------------- pure protocol


def test_framing_is_marlins_xor_worked_by_hand():
    # "H" is 0x48 = 72; "? R": 0x3F ^ 0x20 ^ 0x52 = 0x4D = 77.
    assert sp.frame("H") == "H*72"
    assert sp.frame("? R") == "? R*77"
    assert sp.unframe("? R*77") == "? R" and sp.unframe("? R*108") is None and sp.unframe("? R") is None
    for bad in ("", "S R 1*2", "S\nR", "S " + "9" * 40):
        with pytest.raises(ValueError, match="body"):
            sp.frame(bad)


def test_angles_travel_as_degrees_with_two_decimals():
    assert sp.set_angle(sp.ROLL, math.pi / 2) == "S R 90.00"
    assert sp.set_angle(sp.PITCH, math.radians(-11.456)) == "S P -11.46"
    assert [sp.format_centideg(c) for c in (0, 5, -5, 12345)] == ["0.00", "0.05", "-0.05", "123.45"]
    assert [sp.parse_centideg(t) for t in ("90", "90.5", "-0.05", "1.234", "x", "", "-", "1.")] == [
        9000, 9050, -5, None, None, None, None, None]
    assert sp.calibrate(sp.ROLL, math.radians(2.5)) == "C R 2.50"
    # Servo.h: 0 deg -> 544 us, 180 deg -> 2400 us, 90 deg -> 1472 us.
    assert [sp.pulse_us(c) for c in (0, 9000, 18000)] == [544, 1472, 2400]


def test_travel_comes_from_the_rig_model_rounded_inwards():
    from scenes.kinematics import PITCH_TRAVEL_RAD, ROLL_TRAVEL_RAD

    assert sp.ROLL.travel_rad == ROLL_TRAVEL_RAD and sp.PITCH.travel_rad == PITCH_TRAVEL_RAD
    lo, hi = sp.ROLL.travel_centideg
    assert sp.from_centideg(lo) >= ROLL_TRAVEL_RAD[0] and sp.from_centideg(hi) <= ROLL_TRAVEL_RAD[1]
    assert sp.from_centideg(lo - 1) < ROLL_TRAVEL_RAD[0] and sp.from_centideg(hi + 1) > ROLL_TRAVEL_RAD[1]


@pytest.mark.parametrize("servo, angle", [
    (sp.ROLL, sp.ROLL.travel_rad[1] + 0.01), (sp.ROLL, -1.0), (sp.PITCH, math.nan), (sp.PITCH, "90"),
    (sp.PITCH, math.inf)])
def test_set_angle_refuses_angles_outside_the_travel(servo, angle):
    with pytest.raises(ValueError, match=rf"{servo.name} angle must be within \[.*\] rad"):
        sp.set_angle(servo, angle)


def test_calibrate_refuses_large_offsets():
    with pytest.raises(ValueError, match="sensor_roll offset"):
        sp.calibrate(sp.ROLL, math.radians(20.5))


def test_replies_are_classified():
    assert sp.parse_reply(b"OK S R 90.00*" + str(sp.checksum("OK S R 90.00")).encode() + b"\n").kind is sp.Kind.OK
    err = sp.parse_reply(f"ERR 5 R outside*{sp.checksum('ERR 5 R outside')}\r\n".encode())
    assert (err.kind, err.code, err.words) == (sp.Kind.ERR, 5, ("R outside",))
    assert sp.parse_reply(b"OK S R 90.00*1\n").kind is sp.Kind.CORRUPT
    assert sp.parse_reply(b"\xff\xfe(\n").kind is sp.Kind.GARBAGE
    ok = sp.parse_reply(f"OK S R 90.00*{sp.checksum('OK S R 90.00')}".encode())
    assert sp.answers(ok, "S R 90.00") and not sp.answers(ok, "S R 91.00") and not sp.answers(ok, "S P 90.00")


# ---------------------------------------------------------------------------- over the pty


def test_session_sets_and_reads_back_angles_with_offsets_on_the_board(session):
    seen = []
    twin, board = session(on_angles=lambda roll, pitch: seen.append((roll, pitch)))
    with board:
        board.set_offset("sensor_roll", math.radians(2.5))
        board.set_angles(ROLL_RAD, PITCH_RAD)
        roll, pitch = board.angles()
    assert roll == pytest.approx(ROLL_RAD, abs=WIRE_RESOLUTION_RAD / 2)
    assert pitch == pytest.approx(PITCH_RAD, abs=WIRE_RESOLUTION_RAD / 2)
    assert twin.commands == ["H", "C R 2.50", "S R 90.00", "S P 30.00", "? R", "? P"]
    # The board turns the roll horn to 90 + 2.5 degrees: 544 + 92.5 / 180 * 1856 = 1497.8 us.
    assert twin.horn_rad["sensor_roll"] == pytest.approx(math.radians(92.5))
    assert twin.pulses_us == {"sensor_roll": 1498, "indenter_pitch": 853}
    assert seen == [pytest.approx((ROLL_RAD, PITCH_RAD), abs=WIRE_RESOLUTION_RAD / 2)]


def test_out_of_range_is_refused_before_anything_is_sent(session):
    twin, board = session()
    sent = twin.received
    with pytest.raises(ValueError, match=r"indenter_pitch angle must be within \[-0\.3500, 1\.9208\] rad"):
        board.set_angles(ROLL_RAD, 2.5)  # roll is fine, but nothing may be written
    with pytest.raises(ValueError, match="sensor_roll"):
        board.set_angles(-0.5, PITCH_RAD)
    time.sleep(0.05)
    assert twin.received == sent == ["H*72"]


def test_board_refuses_a_horn_angle_outside_the_pulse_range(session):
    # Within the travel, but roll -5 deg + offset 0 turns the horn below 0 deg.
    twin, board = session()
    with pytest.raises(ServoError, match=r"refused 'S R -5\.00': ERR 6 .*\(PULSE\)"):
        board.set_angles(math.radians(-5.0), PITCH_RAD)
    assert twin.pulses_us["sensor_roll"] is None


def test_query_before_any_set_raises(session):
    _, board = session()
    with pytest.raises(ServoError, match="ERR 8"):
        board.angles()


def test_corrupted_command_is_resent_without_duplicates(session):
    twin, board = session(ServoFaults(corrupt_commands=frozenset({ROLL_LINE})))
    board.set_angles(ROLL_RAD, PITCH_RAD)
    assert twin.commands == ["H", "S R 90.00", "S P 30.00"]
    assert twin.received[ROLL_LINE] == twin.received[ROLL_LINE + 1]  # the same line, written again


def test_corrupted_reply_is_resent(session):
    twin, board = session(ServoFaults(corrupt_replies=frozenset({PITCH_LINE})))
    board.set_angles(ROLL_RAD, PITCH_RAD)
    # The board ran the pitch line, but its answer was damaged: the line runs again (idempotent).
    assert twin.commands == ["H", "S R 90.00", "S P 30.00", "S P 30.00"]


def test_dropped_line_is_written_again_after_the_timeout(session):
    twin, board = session(ServoFaults(drop=frozenset({PITCH_LINE})))
    board.set_angles(ROLL_RAD, PITCH_RAD)
    assert twin.commands == ["H", "S R 90.00", "S P 30.00"]


def test_error_mid_run_raises(session):
    twin, board = session(ServoFaults(error_at=PITCH_LINE, error_text="stall"))
    with pytest.raises(ServoError, match=r"refused 'S P 30\.00': ERR 6 stall"):
        board.set_angles(ROLL_RAD, PITCH_RAD)
    assert twin.commands == ["H", "S R 90.00"]


def test_silent_board_times_out_naming_the_command(session):
    _, board = session(ServoFaults(silent_from=PITCH_LINE))
    with pytest.raises(ServoTimeout, match=r"no answer to 'S P 30\.00' on .* written 3 times"):
        board.set_angles(ROLL_RAD, PITCH_RAD)


def test_garbage_raises_a_clear_error(session):
    _, board = session(ServoFaults(garbage_at=ROLL_LINE))
    with pytest.raises(ServoError, match=r"unreadable lines while waiting for 'S R 90\.00'.*\\xff"):
        board.set_angles(ROLL_RAD, PITCH_RAD)


def test_twin_refuses_overlong_and_unknown_lines():
    import serial

    with ServoTwin() as twin, serial.Serial(twin.port, 115200, timeout=1.0) as port:
        port.write(b"\n")
        assert sp.parse_reply(port.readline()).kind is sp.Kind.READY
        for line, code in ((b"S R " + b"1" * 40, sp.Code.OVERFLOW), (b"S R 90.00*0", sp.Code.CHECKSUM),
                           (sp.frame("S X 1").encode(), sp.Code.SERVO), (sp.frame("Q").encode(), sp.Code.SYNTAX),
                           (sp.frame("S R 9x").encode(), sp.Code.SYNTAX),
                           (sp.frame("S R 200.00").encode(), sp.Code.TRAVEL),
                           (sp.frame("C P 20.01").encode(), sp.Code.OFFSET)):
            port.write(line + b"\n")
            reply = sp.parse_reply(port.readline())
            assert (reply.kind, reply.code) == (sp.Kind.ERR, code), (line, reply)


def test_wrong_device_is_named(session):
    from rig.twins.printer import PrinterTwin

    with PrinterTwin() as printer, pytest.raises(ServoError, match=printer.port):
        ServoBoard(printer.port, reply_timeout_s=0.1, banner_timeout_s=0.2)


def test_missing_port_names_the_port():
    with pytest.raises(ServoError, match="/dev/tactile-sim-no-such-servo-board"):
        ServoBoard("/dev/tactile-sim-no-such-servo-board", banner_timeout_s=0.0)


def test_busy_port_names_the_port(session):
    twin, _ = session()
    with pytest.raises(ServoError, match=twin.port):
        ServoBoard(twin.port, banner_timeout_s=0.0)


# ---------------------------------------------------------------------------- the sketch


def _sketch_constants() -> dict[str, int]:
    text = (SKETCH_DIR / "servo_rig.ino").read_text()
    found = dict(re.findall(r"const long (\w+) = (-?\d+);", text))
    found.update(re.findall(r"#define (MAX_LINE_BYTES|PROTOCOL_VERSION) (\d+)", text))
    found.update((f"E_{name}", value) for name, value in re.findall(r"E_(\w+) = (\d+)", text))
    return {name: int(value) for name, value in found.items()}


def test_sketch_constants_agree_with_python():
    c = _sketch_constants()
    assert (c["ROLL_MIN_CD"], c["ROLL_MAX_CD"]) == sp.ROLL.travel_centideg
    assert (c["PITCH_MIN_CD"], c["PITCH_MAX_CD"]) == sp.PITCH.travel_centideg
    assert {"R": c["ROLL_OFFSET_CD"], "P": c["PITCH_OFFSET_CD"]} == DEFAULT_OFFSETS_CENTIDEG
    assert c["MAX_OFFSET_CD"] == sp.MAX_OFFSET_CENTIDEG
    assert (c["HORN_MIN_CD"], c["HORN_MAX_CD"]) == sp.HORN_RANGE_CENTIDEG
    assert (c["PULSE_MIN_US"], c["PULSE_MAX_US"]) == sp.PULSE_RANGE_US
    assert (c["MAX_LINE_BYTES"], c["PROTOCOL_VERSION"]) == (sp.MAX_LINE_BYTES, sp.PROTOCOL_VERSION)
    assert {name: c[f"E_{name}"] for name in sp.Code.__members__} == {m.name: m.value for m in sp.Code}


#: Header of a stand-in for the Arduino Servo library, with the calls the sketch makes.
SERVO_STAND_IN_H = """#pragma once
#include <stdint.h>
class Servo {
 public:
  uint8_t attach(int pin, int min_us, int max_us);
  void writeMicroseconds(int us);
};
"""
SERVO_STAND_IN_CPP = """#include "Servo.h"
uint8_t Servo::attach(int, int, int) { return 0; }
void Servo::writeMicroseconds(int) {}
"""


def test_sketch_compiles_for_the_mega(tmp_path):
    """Build with Debian's arduino-mk into tmp_path. Debian packages no Servo library, so
    unless one is in ~/Arduino/libraries the sketch is built against a stand-in with the
    library's signatures: this checks the sketch's own code for the ATmega2560, not the
    library."""
    arduino_mk = Path("/usr/share/arduino/Arduino.mk")
    missing = [what for what, ok in (("make", shutil.which("make")), ("avr-gcc", shutil.which("avr-gcc")),
                                     (str(arduino_mk), arduino_mk.exists())) if not ok]
    if missing:
        pytest.skip(f"cannot compile the sketch: {', '.join(missing)} missing "
                    "(apt-get install arduino-mk arduino-core-avr gcc-avr avr-libc)")
    libraries = Path.home() / "Arduino" / "libraries"
    if not (libraries / "Servo").is_dir():
        libraries = tmp_path / "libraries"
        (libraries / "Servo").mkdir(parents=True)
        (libraries / "Servo" / "Servo.h").write_text(SERVO_STAND_IN_H)
        (libraries / "Servo" / "Servo.cpp").write_text(SERVO_STAND_IN_CPP)
    build = tmp_path / "build"
    result = subprocess.run(["make", "-C", str(SKETCH_DIR), f"OBJDIR={build}", f"USER_LIB_PATH={libraries}"],
                            check=False, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert (build / "servo_rig_.hex").is_file() or list(build.glob("*.hex"))
    warnings = [line for line in result.stderr.splitlines() if "servo_rig.ino" in line and "warning" in line]
    assert not warnings, warnings


def test_negative_timeouts_are_refused_before_the_port_is_opened():
    with pytest.raises(ValueError, match="reply_timeout_s must be >= 0 seconds, got -0.5"):
        ServoBoard("/dev/tactile-sim-no-such-servo-board", reply_timeout_s=-0.5)
