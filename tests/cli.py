"""The `mmsclean` command run as a user runs it (a subprocess), for every CLI test."""

from __future__ import annotations

import os
import subprocess
import sys


def mmsclean(
    *args: str,
    env: dict[str, str] | None = None,
    input: str | None = None,
    timeout: float = 600,
) -> subprocess.CompletedProcess:
    """`mmsclean ARGS...` with this environment plus `env`; output captured as text."""
    return subprocess.run(
        [sys.executable, "-m", "app", *args],
        input=input,
        capture_output=True,
        text=True,
        env={**os.environ, **(env or {})},
        timeout=timeout,
    )


def assert_one_line_error(result: subprocess.CompletedProcess, *fragments: str) -> None:
    """A failed command said why in one line on stderr, with no traceback."""
    assert result.returncode != 0
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    for fragment in fragments:
        assert fragment in lines[0]
