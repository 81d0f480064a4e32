"""What the rig does for a protocol, as a list of steps, checked against the envelope.

A capture session is planned whole before any port is opened: :func:`plan` turns a
protocol's taps into :class:`Step` s (home, moves, servo angles, waits, captures, object
changes), and checks every move against the :class:`rig.envelope.SafetyEnvelope`, so a
protocol that would leave the envelope anywhere is refused before anything is sent.
:func:`device_lines` renders a step as the lines the devices would receive (the
``--dry-run`` stream).

Each tap, from the safe height ``layout.home[2]`` (the indenter well above the sensor):

1. move level to above the tap's approach point;
2. turn the servos to the tap's roll and pitch (only up here, where the indenter cannot
   sweep into the sensor);
3. move down to the approach point, :data:`APPROACH_M` back from the contact along the
   tap's normal;
4. press along -normal to the tap's depth, slowly (:data:`PRESS_FEED_M_S`);
5. wait for the moves to finish (``M400``) and capture;
6. back out to the approach point, slowly, and up to the safe height.

The session starts by homing (``G28``), rising to the safe height and moving to
``layout.home``, where the no-contact background is captured first.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scenes.kinematics import RigLayout, head_for_tap, sensor_to_world

from . import gcode
from . import servo_protocol as sp
from .envelope import EnvelopeError, SafetyEnvelope

#: Where a press starts: this far out from the contact point along the normal, metres.
APPROACH_M = 0.008
#: Feed rate of moves away from the sensor, m/s (1800 mm/min).
TRAVEL_FEED_M_S = 0.03
#: Feed rate of a press and of backing out of it, m/s (120 mm/min).
PRESS_FEED_M_S = 0.002

#: Step kinds.
HOME, MOVE, SERVOS, WAIT, CAPTURE, MOUNT = "home", "move", "servos", "wait", "capture", "mount"


@dataclass(frozen=True)
class Step:
    """One thing the rig does.

    kind : one of HOME, MOVE, SERVOS, WAIT, CAPTURE, MOUNT.
    head : (3,) world metres, a MOVE's target.
    feed : m/s, a MOVE's feed rate.
    roll, pitch : rad, a SERVOS step's angles.
    tap : the tap index a step belongs to (None: the session's start, the background).
    obj : the indenter a MOUNT puts on (and a step's indenter).
    press : a MOVE that presses into the membrane (or backs out of it).
    """

    kind: str
    tap: int | None = None
    obj: str | None = None
    head: tuple[float, float, float] | None = None
    feed: float | None = None
    roll: float | None = None
    pitch: float | None = None
    press: bool = False


def _move(head, feed, tap=None, obj=None, press=False) -> Step:
    return Step(MOVE, tap=tap, obj=obj, head=tuple(float(v) for v in head), feed=feed, press=press)


def waypoints(tap, vertices: np.ndarray, layout: RigLayout) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A tap's head positions, (3,) world metres each: the press, the approach point
    (:data:`APPROACH_M` out from the contact along the normal) and the point above it at
    the safe height ``layout.home[2]``."""
    press = head_for_tap(tap, vertices, layout)
    n_world = sensor_to_world(tap.sensor_roll) @ np.asarray(tap.normal)
    approach = press + (APPROACH_M + tap.depth) * n_world
    return press, approach, np.array([approach[0], approach[1], layout.home[2]])


def plan(taps, vertices: dict[str, np.ndarray], layout: RigLayout, envelope: SafetyEnvelope | None = None,
         background: bool = True) -> list[Step]:
    """The steps that carry out ``taps`` (in order), checked against ``envelope``.

    Parameters
    ----------
    taps : sequence of scenes.taps.Tap, the taps still to do.
    vertices : indenter name -> (V, 3) its mesh's vertices, metres.
    envelope : every move is checked against it (EnvelopeError naming the tap and move);
        None checks nothing (tests of the steps alone).
    background : start with a capture of the no-contact image.
    """
    home = np.asarray(layout.home, dtype=np.float64)
    safe_z = float(home[2])
    steps = [Step(HOME)]
    homed = layout.head_position(np.zeros(3))
    rise = np.array([homed[0], homed[1], safe_z])
    steps += [_move(rise, TRAVEL_FEED_M_S), _move(home, TRAVEL_FEED_M_S)]
    mounted, roll, pitch = None, 0.0, 0.0
    steps += [Step(WAIT), Step(SERVOS, roll=roll, pitch=pitch)]
    if background:
        steps += [Step(WAIT), Step(CAPTURE)]
    for tap in taps:
        if tap.object not in vertices:
            raise ValueError(f"tap {tap.index} presses {tap.object!r}, but no mesh was given for it; have "
                             f"{sorted(vertices)}")
        press, approach, above = waypoints(tap, vertices[tap.object], layout)
        where = dict(tap=tap.index, obj=tap.object)
        if tap.object != mounted:
            steps += [Step(WAIT), Step(MOUNT, **where)]
            mounted = tap.object
        steps.append(_move(above, TRAVEL_FEED_M_S, **where))
        if (tap.sensor_roll, tap.indenter_pitch) != (roll, pitch):
            roll, pitch = tap.sensor_roll, tap.indenter_pitch
            steps += [Step(WAIT), Step(SERVOS, roll=roll, pitch=pitch, **where)]
        steps += [
            _move(approach, TRAVEL_FEED_M_S, **where),
            _move(press, PRESS_FEED_M_S, press=True, **where),
            Step(WAIT, **where),
            Step(CAPTURE, **where),
            _move(approach, PRESS_FEED_M_S, press=True, **where),
            _move(above, TRAVEL_FEED_M_S, **where),
        ]
    steps += [_move(home, TRAVEL_FEED_M_S), Step(WAIT)]
    if envelope is not None:
        check(steps, envelope, home_obj=taps[0].object if len(taps) else None)
    return steps


def describe(step: Step) -> str:
    """Where a step is, for messages: ``tap 7 (cone)`` or ``the session's start``."""
    return f"tap {step.tap} ({step.obj})" if step.tap is not None else "the session's start"


def check(steps: list[Step], envelope: SafetyEnvelope, home_obj: str | None = None) -> None:
    """EnvelopeError unless every move of ``steps``, from where the previous one left the
    head, keeps the indenter in the envelope (with the servos and indenter as set then)."""
    head, roll, pitch, obj = None, 0.0, 0.0, home_obj
    for i, step in enumerate(steps):
        if step.kind == HOME:
            head = envelope.layout.head_position(np.zeros(3))
        elif step.kind == SERVOS:
            roll, pitch = step.roll, step.pitch
            for servo, angle in ((sp.ROLL, roll), (sp.PITCH, pitch)):
                try:
                    sp.check_angle(servo, angle)
                except ValueError as exc:
                    raise EnvelopeError(f"{describe(step)}: {exc}") from None
            if obj is not None:
                envelope.check_pose(obj, head, pitch, roll, f"{describe(step)}: turning the servos")
        elif step.kind == MOUNT:
            obj = step.obj
        elif step.kind == MOVE:
            target = np.asarray(step.head)
            where = f"{describe(step)}: move {i} to {np.round(target * 1e3, 1).tolist()} mm (world)"
            if obj is None:
                envelope.check_head(target, where)
            else:
                envelope.check_move(obj, head, target, pitch, roll, where, press=step.press)
            head = target


def device_lines(step: Step, layout: RigLayout) -> list[tuple[str, str]]:
    """The lines a step sends, as ``(device, line)``: ``printer`` G-code (unframed),
    ``servos`` commands (framed as sent), ``camera`` and ``operator`` actions."""
    if step.kind == HOME:
        return [("printer", gcode.home())]
    if step.kind == MOVE:
        return [("printer", gcode.linear_move(layout.printer_position(step.head), step.feed))]
    if step.kind == WAIT:
        return [("printer", gcode.finish_moves())]
    if step.kind == SERVOS:
        return [("servos", sp.frame(sp.set_angle(sp.ROLL, step.roll))),
                ("servos", sp.frame(sp.set_angle(sp.PITCH, step.pitch)))]
    if step.kind == CAPTURE:
        return [("camera", "capture background" if step.tap is None else f"capture tap {step.tap}")]
    if step.kind == MOUNT:
        return [("operator", f"mount the {step.obj} indenter")]
    raise ValueError(f"step kind must be one of {[HOME, MOVE, SERVOS, WAIT, CAPTURE, MOUNT]}, got {step.kind!r}")
