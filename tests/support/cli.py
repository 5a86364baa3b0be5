"""The command line as a user runs it, from a test: `cadence …` in a subprocess of this checkout."""

from __future__ import annotations

import signal
import subprocess
import sys


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "cadence", *args], capture_output=True, text=True, timeout=300
    )


def as_in_a_terminal() -> None:
    """A child's SIGINT as a terminal's foreground job has it (``preexec_fn``). A job a shell started in
    the background, without job control, ignores SIGINT, and so do its children: a test run from one
    (CI, a script with ``&``) would send a Ctrl-C that its demo, rightly, never sees."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def as_in_the_background() -> None:
    """A child's SIGINT as a non-interactive shell's background job has it (``cadence demo … &`` in a
    script): ignored, by POSIX rule (``preexec_fn``). SIGTERM must still end it as Ctrl-C would."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
