"""The Marlin driver against its twin on a real pty with real pyserial, and the pure G-code
functions on their own (checksums worked out by hand first)."""

from __future__ import annotations

import functools
import math
import operator
import time

import numpy as np
import pytest

pytest.importorskip("serial", reason="pyserial is not installed (pip install '.[rig]')")

from rig import gcode
from rig.gcode import Kind, parse_reply
from rig.marlin import MarlinPrinter, PrinterError, PrinterTimeout
from rig.twins.printer import PrinterTwin, TwinFaults

#: Reply timeout for the twin, seconds: it answers in well under a millisecond.
TWIN_REPLY_TIMEOUT_S = 0.4
#: The twin sends its banner as soon as the host writes, seconds.
TWIN_BANNER_TIMEOUT_S = 1.0
#: Wait for the twin's thread to act on a line that gets no answer, seconds.
TWIN_SETTLE_S = 1.0
#: M114 prints millimetres with two decimals.
M114_RESOLUTION_M = 0.01e-3
#: After connecting, the driver has sent N0 M110 N0, N1 G21, N2 G90: the next line is N3.
FIRST_LINE = 3
FEED_M_S = 0.02
#: Commanded positions, metres: multiples of 10 µm so that M114 reports them exactly.
TARGETS_M = np.array([[0.010, 0.020, 0.005], [0.012, 0.020, 0.004], [0.012, 0.021, 0.003], [0.000, 0.000, 0.010]])


@pytest.fixture
def session():
    """Make a twin with faults and a connected printer; close both afterwards."""
    opened = []

    def make(faults: TwinFaults | None = None, **kwargs):
        twin = PrinterTwin(faults or TwinFaults(), **kwargs)
        opened.append(twin)
        printer = MarlinPrinter(twin.port, reply_timeout_s=TWIN_REPLY_TIMEOUT_S,
                                banner_timeout_s=TWIN_BANNER_TIMEOUT_S)
        opened.append(printer)
        return twin, printer

    yield make
    for thing in reversed(opened):
        thing.close()


def _run_moves(printer: MarlinPrinter) -> None:
    printer.home()  # N3
    for target in TARGETS_M:  # N4 ..
        printer.move_to(target, FEED_M_S)
    printer.wait_for_moves()


def _assert_moves_exactly(twin: PrinterTwin, targets: np.ndarray) -> None:
    """The twin ran each commanded move once, in order, on consecutive line numbers."""
    moves = twin.moves
    assert len(moves) == len(targets), [m.command for m in moves]
    np.testing.assert_allclose([m.position_m for m in moves], targets, atol=1e-9)
    numbers = [n for n, _ in twin.lines]
    assert numbers == list(range(numbers[0], numbers[0] + len(numbers))), numbers


# ---------------------------------------------------------------------------- pure protocol


def test_checksum_is_the_xor_of_the_bytes_worked_by_hand():
    # "N3 T0": N=0x4E, 3=0x33, space=0x20, T=0x54, 0=0x30; 0x4E^0x33^0x20^0x54^0x30 = 0x39.
    assert 0x4E ^ 0x33 ^ 0x20 ^ 0x54 ^ 0x30 == 57
    assert gcode.checksum("N3 T0") == 57
    # The same line and checksum are the RepRap wiki's example of a framed line.
    assert gcode.frame(3, "T0") == "N3 T0*57"
    body = "N0 M110 N0"
    assert gcode.frame(0, "M110 N0") == f"{body}*{functools.reduce(operator.xor, body.encode())}"
    assert gcode.checksum("") == 0


def test_frame_refuses_what_the_firmware_would_misread():
    for bad in ("G1 X1 ; comment", "G1*5", "G1\nG28", "", "   "):
        with pytest.raises(ValueError, match="command"):
            gcode.frame(1, bad)
    with pytest.raises(ValueError, match="line_number"):
        gcode.frame(-1, "G28")


def test_commands_are_marlin_gcode():
    assert [gcode.home(), gcode.absolute_positioning(), gcode.millimetre_units()] == ["G28", "G90", "G21"]
    assert [gcode.finish_moves(), gcode.quick_stop(), gcode.emergency_stop()] == ["M400", "M410", "M112"]
    assert [gcode.report_position(), gcode.set_line_number()] == ["M114", "M110 N0"]


def test_linear_move_converts_si_to_millimetres_and_mm_per_min():
    # 10 mm/s = 600 mm/min; 1 µm steps are kept.
    assert gcode.linear_move([0.010, 0.020, 0.005], 0.010) == "G1 X10.000 Y20.000 Z5.000 F600.0"
    assert gcode.linear_move(np.array([-0.0015, 0.0, 0.000001]), 0.05) == "G1 X-1.500 Y0.000 Z0.001 F3000.0"


@pytest.mark.parametrize("xyz, feed, name", [
    ([math.nan, 0.0, 0.0], 0.01, "xyz_m"),
    ([0.0, math.inf, 0.0], 0.01, "xyz_m"),
    ([0.0, 0.0], 0.01, "xyz_m"),
    ([0.0, 0.0, 0.0], -0.01, "feed_m_s"),
    ([0.0, 0.0, 0.0], 0.0, "feed_m_s"),
    ([0.0, 0.0, 0.0], math.nan, "feed_m_s"),
    ([0.0, 0.0, 0.0], math.inf, "feed_m_s"),
])
def test_linear_move_refuses_bad_input(xyz, feed, name):
    with pytest.raises(ValueError, match=name):
        gcode.linear_move(xyz, feed)


def test_parse_position_reads_millimetres_before_count():
    reply = "X:10.00 Y:20.00 Z:5.00 E:0.00 Count X:800 Y:1600 Z:2000"
    np.testing.assert_allclose(gcode.parse_position(reply), [0.010, 0.020, 0.005])
    np.testing.assert_allclose(gcode.parse_position("X:-1.5 Y:0.00 Z:0.25 E:0.00 Count X:9 Y:9 Z:9"),
                               [-0.0015, 0.0, 0.00025])
    with pytest.raises(ValueError, match="reply"):
        gcode.parse_position("ok")


@pytest.mark.parametrize("raw, kind, number", [
    (b"ok\n", Kind.OK, None),
    (b"ok N5 P15 B3\r\n", Kind.OK, None),
    (b"Resend: 5\n", Kind.RESEND, 5),
    (b"rs 7\n", Kind.RESEND, 7),
    (b"Error:checksum mismatch, Last Line: 4\n", Kind.LINE_ERROR, 4),
    (b"Error:Line Number is not Last Line Number+1, Last Line: 4\n", Kind.LINE_ERROR, 4),
    (b"Error:No Checksum with line number, Last Line: 9\n", Kind.LINE_ERROR, 9),
    (b"Error:MAXTEMP triggered\n", Kind.ERROR, None),
    (b"echo:busy: processing\n", Kind.BUSY, None),
    (b"busy: processing\n", Kind.BUSY, None),
    (b'echo:Unknown command: "G99"\n', Kind.ECHO, None),
    (b"start\n", Kind.START, None),
    (b"X:1.00 Y:2.00 Z:3.00 E:0.00 Count X:80 Y:160 Z:1200\n", Kind.DATA, None),
    (b"\xff\xfe\x81\n", Kind.GARBAGE, None),
    (b"ok\x00\x01\n", Kind.GARBAGE, None),
])
def test_parse_reply_tags_each_kind(raw, kind, number):
    reply = parse_reply(raw)
    assert (reply.kind, reply.number) == (kind, number)


def test_twin_faults_refuse_bad_input():
    with pytest.raises(ValueError, match="corrupt_rate"):
        TwinFaults(corrupt_rate=1.5)
    with pytest.raises(ValueError, match="busy_s"):
        TwinFaults(busy_s=-1.0)


# ---------------------------------------------------------------------------- over the pty


def test_session_returns_the_commanded_position_in_metres(session):
    seen = []
    twin, printer = session(on_move=seen.append)
    with printer:
        _run_moves(printer)
        position = printer.position()
    np.testing.assert_allclose(position, TARGETS_M[-1], atol=M114_RESOLUTION_M / 2)
    _assert_moves_exactly(twin, TARGETS_M)
    assert [n for n, _ in twin.lines][:FIRST_LINE] == [0, 1, 2]
    assert [command for _, command in twin.lines][:FIRST_LINE + 1] == ["M110 N0", "G21", "G90", "G28"]
    np.testing.assert_allclose(seen, np.vstack([np.zeros(3), TARGETS_M]), atol=1e-9)  # G28, then moves
    assert twin.moves[0].feed_m_s == pytest.approx(FEED_M_S)


def test_driver_accepts_an_open_serial_port():
    import serial

    with PrinterTwin() as twin, serial.Serial(twin.port, 115200) as port:
        printer = MarlinPrinter(port, reply_timeout_s=TWIN_REPLY_TIMEOUT_S, banner_timeout_s=TWIN_BANNER_TIMEOUT_S)
        printer.move_to([0.001, 0.002, 0.003], FEED_M_S)
        np.testing.assert_allclose(printer.position(), [0.001, 0.002, 0.003], atol=M114_RESOLUTION_M / 2)
        printer.close()
        assert port.is_open  # not the driver's to close


def test_corrupted_checksums_are_resent_without_duplicates_or_gaps(session):
    twin, printer = session(TwinFaults(corrupt_lines=frozenset({0, FIRST_LINE + 1, FIRST_LINE + 2})))
    _run_moves(printer)
    _assert_moves_exactly(twin, TARGETS_M)
    assert twin.rejected == [(n, "checksum mismatch") for n in (0, FIRST_LINE + 1, FIRST_LINE + 2)]


def test_resend_without_ok_is_followed_after_a_grace(session):
    # Some Marlin 2.0.x builds send no ok after Resend; the driver resends after RESEND_OK_GRACE_S.
    twin, printer = session(TwinFaults(corrupt_lines=frozenset({FIRST_LINE + 1}), ok_after_resend=False))
    _run_moves(printer)
    _assert_moves_exactly(twin, TARGETS_M)
    assert twin.rejected == [(FIRST_LINE + 1, "checksum mismatch")]


def test_random_corruption_is_recovered(session):
    twin, printer = session(TwinFaults(corrupt_rate=0.3, seed=7))
    _run_moves(printer)
    _assert_moves_exactly(twin, TARGETS_M)
    assert len(twin.rejected) >= 2


def test_dropped_line_is_written_again_after_the_timeout(session):
    twin, printer = session(TwinFaults(drop_lines=frozenset({FIRST_LINE + 2})))
    _run_moves(printer)
    _assert_moves_exactly(twin, TARGETS_M)
    assert twin.dropped == [FIRST_LINE + 2] and twin.rejected == []


def test_lost_ok_does_not_run_the_move_twice(session):
    # The twin runs the move but its ok is lost: the driver writes the line again, the
    # firmware refuses it as a repeated line number and asks for the next one.
    twin, printer = session(TwinFaults(mute_lines=frozenset({FIRST_LINE + 1})))
    _run_moves(printer)
    _assert_moves_exactly(twin, TARGETS_M)
    assert twin.rejected == [(FIRST_LINE + 1, "Line Number is not Last Line Number+1")]


def test_error_mid_run_raises(session):
    twin, printer = session(TwinFaults(error_at_line=FIRST_LINE + 2))
    with pytest.raises(PrinterError, match="MAXTEMP triggered"):
        _run_moves(printer)
    assert len(twin.moves) == 1


def test_garbage_raises_a_clear_error(session):
    _, printer = session(TwinFaults(garbage_at_line=FIRST_LINE + 1))
    printer.home()
    with pytest.raises(PrinterError, match=r"unreadable lines .*G1 X10\.000.*\\xff"):
        printer.move_to(TARGETS_M[0], FEED_M_S)


def test_silent_printer_times_out_naming_the_command(session):
    _, printer = session(TwinFaults(silent_from_line=FIRST_LINE + 1))
    printer.home()
    with pytest.raises(PrinterTimeout, match=r"'G1 X10\.000 Y20\.000 Z5\.000 F1200\.0' \(line N4\)"):
        printer.move_to(TARGETS_M[0], FEED_M_S)


def test_restart_mid_run_raises_instead_of_replaying_moves(session):
    twin, printer = session(TwinFaults(restart_at_line=FIRST_LINE + 2))
    with pytest.raises(PrinterError, match="restarted"):
        _run_moves(printer)
    assert len(twin.moves) == 1


def test_resend_of_an_acknowledged_line_is_refused(session):
    # A firmware that lost its count asks for N1 again; resending it could run a move twice.
    twin, printer = session(TwinFaults(forget_count_at_line=FIRST_LINE + 1))
    printer.home()
    with pytest.raises(PrinterError, match="N1, already acknowledged"):
        printer.move_to(TARGETS_M[0], FEED_M_S)
    assert twin.moves == []


def test_send_refuses_m110(session):
    _, printer = session()
    with pytest.raises(ValueError, match="command must not be M110"):
        printer.send("M110 N7")


def test_busy_extends_the_wait(session):
    # M400 answers only after 3 reply timeouts, sending busy: meanwhile.
    twin, printer = session(TwinFaults(busy_s=3 * TWIN_REPLY_TIMEOUT_S))
    _run_moves(printer)
    assert [command for _, command in twin.lines].count("M400") == 1  # never written again


def test_emergency_stop_does_not_wait_and_halts(session):
    twin, printer = session()
    printer.move_to(TARGETS_M[0], FEED_M_S)
    printer.emergency_stop()
    deadline = time.monotonic() + TWIN_SETTLE_S
    while not twin.halted and time.monotonic() < deadline:
        time.sleep(0.01)
    assert twin.halted
    with pytest.raises(PrinterError, match="M112"):
        printer.position()


def test_quick_stop_is_acknowledged(session):
    twin, printer = session()
    printer.quick_stop()
    assert twin.lines[-1] == (FIRST_LINE, "M410")


def test_missing_port_names_the_port():
    with pytest.raises(PrinterError, match="/dev/tactile-sim-no-such-printer"):
        MarlinPrinter("/dev/tactile-sim-no-such-printer", banner_timeout_s=0.0)


def test_busy_port_names_the_port(session):
    twin, _ = session()
    with pytest.raises(PrinterError, match=twin.port):
        MarlinPrinter(twin.port, banner_timeout_s=0.0)


def test_negative_timeouts_are_refused_before_the_port_is_opened():
    with pytest.raises(ValueError, match="reply_timeout_s must be >= 0 seconds, got -1"):
        MarlinPrinter("/dev/tactile-sim-no-such-printer", reply_timeout_s=-1)
    with pytest.raises(ValueError, match="banner_timeout_s must be >= 0 seconds, got nan"):
        MarlinPrinter("/dev/tactile-sim-no-such-printer", banner_timeout_s=math.nan)


def test_a_port_that_fails_in_its_drain_raises_the_drivers_error():
    """pyserial's flush() drains through termios, whose error is not an OSError: a cable
    pulled mid-write must still come out as the driver's error naming the port."""
    import termios

    from rig.serial_lines import SerialLines

    class Unplugged:
        port = "/dev/ttyUSB0"
        timeout = None

        def write(self, data):
            return len(data)

        def flush(self):
            raise termios.error(5, "Input/output error")

        def read(self, n):
            raise termios.error(5, "Input/output error")

        in_waiting = 0

    link = SerialLines(Unplugged(), 115200, 1.0, "printer", PrinterError)
    with pytest.raises(PrinterError, match="cannot write 'M105' to /dev/ttyUSB0.*Input/output error"):
        link.write("M105")
    with pytest.raises(PrinterError, match="cannot read from /dev/ttyUSB0"):
        link.read_line(time.monotonic() + 1.0)
