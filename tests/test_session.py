"""The test session's own set-up (tests/conftest.py)."""

import signal
import subprocess
import sys


def test_processes_the_tests_start_handle_ctrl_c_even_when_the_session_was_started_ignoring_it():
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    code = "import signal; print(signal.getsignal(signal.SIGINT) is signal.default_int_handler)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "True"
