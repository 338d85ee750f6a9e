"""A real planner daemon for the package's tests.

It runs the ``planner-service`` binary of this repository (``$EBMPC_PLANNER_BIN``, or
``target/debug/planner-service``: ``cargo build --bins`` makes it; the tests fail without it,
they never skip) on a free loopback port with multicast scouting off (every ebmpc process
has it off), in a temporary data directory. It is stopped after each test, also when the test
fails, and on Linux it is also killed when the test process dies (parent-death signal), so no
daemon outlives a killed test run.
"""

from __future__ import annotations

import ctypes
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional

import pytest

REPO = Path(__file__).resolve().parents[2]
PR_SET_PDEATHSIG = 1


def planner_binary() -> Path:
    path = Path(os.environ.get("EBMPC_PLANNER_BIN", REPO / "target" / "debug" / "planner-service"))
    if not path.is_file():
        pytest.fail(f"no planner-service binary at {path}: run `cargo build --bins` "
                    "or set EBMPC_PLANNER_BIN")
    return path


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def _die_with_parent() -> None:
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)


@dataclass
class Daemon:
    endpoint: str
    process: "subprocess.Popen[bytes]"
    log_path: Path

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self) -> Optional[int]:
        """SIGTERM, then SIGKILL after 30 s; the exit status."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        return self.process.returncode


@pytest.fixture
def daemon(tmp_path: Path) -> Iterator[Daemon]:
    """A planner serving on a free port; its sizes come from each test's attach overrides."""
    config = tmp_path / "planner.toml"
    config.write_text('planner_id = "py-pkg"\n')
    endpoint = free_endpoint()
    log_path = tmp_path / "planner.log"
    with open(log_path, "wb") as log:
        process = subprocess.Popen(
            [str(planner_binary()), "serve", "--config", str(config),
             "--data-dir", str(tmp_path / "data"), "--listen", endpoint],
            stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            env=dict(os.environ, RUST_LOG="info,zenoh=warn"),
            preexec_fn=_die_with_parent,
        )
    daemon = Daemon(endpoint, process, log_path)
    try:
        deadline = time.monotonic() + 60
        while "planner serving" not in daemon.log():
            if process.poll() is not None:
                pytest.fail(f"planner exited ({process.returncode}):\n{daemon.log()}")
            if time.monotonic() > deadline:
                pytest.fail(f"planner not serving within 60 s:\n{daemon.log()}")
            time.sleep(0.05)
        yield daemon
    finally:
        status = daemon.stop()
    assert status == 0, f"planner exit status {status}:\n{daemon.log()}"
