"""The tapping rig: drivers for the printer, the servo board and the camera, their software
twins, and the session that runs a protocol on them and writes a capture.

The public modules are listed in ``__all__``; import each by its name (``from rig import
x`` or ``rig.x``). Nothing is imported here, so importing one module loads no other.
"""

__all__ = [
    "align", "camera", "capture", "envelope", "gcode", "marlin", "plan", "serial_lines",
    "servo_protocol", "servos", "session", "twins", "virtual",
]
