"""The CLI run in the test's own process: ``main`` with its output captured, as a finished command's.

A run through the console script costs about 3 s of start-up (the interpreter, torch, yourdfpy); each test
file keeps at least one run through the real entry point and runs the rest here, where the same ``main``
parses the same arguments and returns the same exit code.
"""

from __future__ import annotations

import contextlib
import io
from dataclasses import dataclass

from hybrid_kinematics_ros.cli.main import main


@dataclass(frozen=True)
class Finished:
    returncode: int
    stdout: str
    stderr: str


def cli(*args: str) -> Finished:
    """``hybrid-kinematics *args`` in this process; argparse's own exits (bad flags) become the exit code."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main([str(a) for a in args])
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
    return Finished(code, out.getvalue(), err.getvalue())
