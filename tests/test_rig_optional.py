"""The rig's serial devices need pyserial (the ``rig`` extra); without it the command line
still loads, and opening a device says what is missing."""

import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent("""
    import sys
    sys.modules["serial"] = None  # as if pyserial were not installed
    from scenes.cli import main
    try:
        main(["rig", "run", "--help"])
    except SystemExit as exc:
        assert exc.code == 0, exc.code
    from rig.marlin import PrinterError
    from rig.serial_lines import open_port
    try:
        open_port("/dev/ttyUSB9", 115200, 1.0, "printer", PrinterError)
    except PrinterError as exc:
        print("ERROR:", exc)
""")


def test_the_cli_loads_without_pyserial_and_a_port_says_why():
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "usage:" in out.stdout
    error = out.stdout.splitlines()[-1]
    assert error.startswith("ERROR:") and "pyserial is not installed" in error and "/dev/ttyUSB9" in error
