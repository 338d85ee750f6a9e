"""``Planner.local``: the package starts a planner daemon of its own, talks to it, stops it, and
never leaves it behind (not even when the interpreter is killed); each way it can fail to start
raises an error a user can act on.

The daemon is this repository's build (``$EBMPC_PLANNER_BIN``, as in conftest), which is also
what :func:`ebmpc.local.find_planner_binary` honours before the installed one.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

import ebmpc
from conftest import planner_binary
from ebmpc import local


#: A small search: these tests check the daemon's life, not planning.
SMALL = {"population": 20, "elites": 4, "horizon": 5, "cem_iterations": 2}


@pytest.fixture(autouse=True)
def bundled_binary(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(local.BINARY_ENV, str(planner_binary()))


def alive(pid: int) -> bool:
    """Whether process ``pid`` exists and is not a zombie."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state != "Z"


def test_a_local_planner_serves_a_run_and_stops_with_the_block(tmp_path: Path) -> None:
    with ebmpc.Planner.local(tmp_path / "data") as planner:
        daemon = planner.daemon
        assert daemon is not None and daemon.running
        assert daemon.endpoint.startswith("tcp/127.0.0.1:")
        (report,) = planner.status()
        assert report["planner_id"] == local.LOCAL_PLANNER_ID
        with planner.attach("local-run", "cartpole", overrides=SMALL) as agent:
            action = agent.act([0.0, 0.0, 0.0, 0.0])
            assert len(action) == 1
            finished = agent.end([0.0, 0.01, 0.0, 0.0], 1.0, "time_limit")
            assert finished is not None and finished.steps == 1
    assert not daemon.running and daemon.process.returncode == 0, daemon.log()
    assert "SIGTERM received" in daemon.log()
    # The run is kept in the data directory: a second local planner resumes it.
    with ebmpc.Planner.local(tmp_path / "data") as planner:
        with planner.attach("local-run", "cartpole", overrides=SMALL) as agent:
            assert (agent.episode, agent.episodes_done) == (1, 1)
            assert agent.planner_id == local.LOCAL_PLANNER_ID


def test_a_data_directory_served_by_another_planner_is_refused(tmp_path: Path) -> None:
    with ebmpc.Planner.local(tmp_path / "data"):
        with pytest.raises(ebmpc.DataDirLockedError) as caught:
            ebmpc.Planner.local(tmp_path / "data")
    assert str(tmp_path / "data") in str(caught.value)
    assert "already serves" in caught.value.log_tail


def test_a_taken_port_is_refused_before_starting(tmp_path: Path) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        with pytest.raises(ebmpc.PortInUseError, match=f"port {port}"):
            ebmpc.Planner.local(tmp_path / "data", port=port)


def test_a_planner_that_exits_at_start_shows_its_last_log_lines(tmp_path: Path) -> None:
    fake = tmp_path / "planner-service"
    fake.write_text("#!/bin/sh\necho 'starting'\necho 'error: the disk is on fire' >&2\nexit 3\n")
    fake.chmod(0o755)
    with pytest.raises(ebmpc.PlannerStartError) as caught:
        ebmpc.Planner.local(tmp_path / "data", binary=fake)
    assert "status 3" in str(caught.value)
    assert "the disk is on fire" in str(caught.value)
    assert "the disk is on fire" in caught.value.log_tail


def test_no_binary_says_how_to_get_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(local.BINARY_ENV, str(tmp_path / "nothing-here"))
    with pytest.raises(ebmpc.PlannerNotFoundError, match="not an executable"):
        ebmpc.Planner.local(tmp_path / "data")
    monkeypatch.delenv(local.BINARY_ENV)
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.setattr(local.sysconfig, "get_path", lambda *a, **k: str(tmp_path))
    monkeypatch.setattr(local.sys, "executable", str(tmp_path / "python"))
    with pytest.raises(ebmpc.PlannerNotFoundError, match="pip install ./python"):
        local.find_planner_binary()


def test_the_daemon_does_not_outlive_a_killed_interpreter(tmp_path: Path) -> None:
    script = textwrap.dedent(f"""
        import sys, time
        import ebmpc
        planner = ebmpc.Planner.local({str(tmp_path / "data")!r})
        print(planner.daemon.process.pid, flush=True)
        time.sleep(600)
    """)
    child = subprocess.Popen(
        [sys.executable, "-c", script], stdout=subprocess.PIPE, text=True,
        env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1])),
    )
    try:
        assert child.stdout is not None
        pid = int(child.stdout.readline())
        assert alive(pid)
        child.send_signal(signal.SIGKILL)
        child.wait()
        deadline = time.monotonic() + 10
        while alive(pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not alive(pid), "the daemon outlived its interpreter"
    finally:
        child.kill()
        child.wait()
    log = (tmp_path / "data" / "planner.log").read_text()
    assert "standard input closed" in log, log


def test_the_data_directory_is_per_user_unless_told(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(local.DATA_DIR_ENV, raising=False)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    if sys.platform.startswith("linux"):
        assert local.default_data_dir() == tmp_path / "xdg" / "ebmpc"
        monkeypatch.setenv("XDG_DATA_HOME", "relative/ignored")
        assert local.default_data_dir() == Path.home() / ".local" / "share" / "ebmpc"
    monkeypatch.setenv(local.DATA_DIR_ENV, str(tmp_path / "mine"))
    assert local.default_data_dir() == tmp_path / "mine"


def test_the_daemon_gets_none_of_the_users_ebmpc_settings(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("EBMPC_CONNECT", "tcp/10.0.0.1:7447")
    assert "EBMPC_CONNECT" not in local._daemon_env()
