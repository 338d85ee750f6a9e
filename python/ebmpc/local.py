"""A planner daemon of this machine, started and stopped by the package itself.

The wheel of this package carries the ``planner-service`` binary (built from the Rust workspace
by maturin, as ruff and uv ship theirs) in the environment's scripts directory (on ``PATH``
in an activated venv). :class:`LocalDaemon` starts it on a free loopback port
with multicast scouting off (every ebmpc process has it off), waits until it serves, and stops
it with SIGTERM and a bounded wait. The daemon never outlives the Python process that started
it: it is started with ``--exit-on-stdin-close`` and a pipe on its standard input whose write
end only this process holds, so when this process ends in any way (also SIGKILL) the kernel
closes the pipe and the daemon stops as on SIGTERM, syncing what it stored.

Runs are kept under :func:`default_data_dir` unless another directory is given, so a second
start on the same directory resumes them.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import sysconfig
import time
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Union

from .errors import (
    DataDirLockedError,
    PlannerNotFoundError,
    PlannerStartError,
    PortInUseError,
)

#: The daemon binary's name (a cargo bin target of the workspace).
BINARY = "planner-service"
#: The environment variable naming a planner binary to use instead of the bundled one.
BINARY_ENV = "EBMPC_PLANNER_BIN"
#: The environment variable naming the data directory instead of :func:`default_data_dir`.
DATA_DIR_ENV = "EBMPC_DATA_DIR"
#: The id of a local planner: one per data directory (the daemon locks it under this id).
LOCAL_PLANNER_ID = "local"
#: What the daemon logs once it serves.
SERVING_LINE = "planner serving"
#: Free ports tried when the one picked is taken before the daemon binds it.
PORT_ATTEMPTS = 3
#: Log lines kept in a start error.
LOG_TAIL_LINES = 20


def _exe(name: str) -> str:
    return name + (".exe" if sys.platform == "win32" else "")


def find_planner_binary() -> Path:
    """The ``planner-service`` binary: ``$EBMPC_PLANNER_BIN`` if set, else the one installed
    with this package (the scripts directory of its environment, or of the user scheme for a
    ``pip install --user``), else one on ``PATH``.

    Raises :class:`PlannerNotFoundError` saying where it looked and how to get one.
    """
    explicit = os.environ.get(BINARY_ENV)
    if explicit:
        path = Path(explicit)
        if path.is_file() and os.access(path, os.X_OK):
            return path
        raise PlannerNotFoundError(f"${BINARY_ENV} is {explicit}, which is not an executable file")
    name = _exe(BINARY)
    places: List[Path] = []
    # Where pip put the package's scripts: this interpreter's environment first.
    places.append(Path(sysconfig.get_path("scripts")))
    try:
        user_scheme = sysconfig.get_preferred_scheme("user")  # Python 3.10+
    except AttributeError:
        user_scheme = "nt_user" if os.name == "nt" else "posix_user"
    try:
        places.append(Path(sysconfig.get_path("scripts", scheme=user_scheme)))
    except KeyError:
        pass
    # The interpreter's own directory (a venv's bin/ when sysconfig says otherwise).
    places.append(Path(sys.executable).parent)
    for place in places:
        candidate = place / name
        if candidate.is_file() and os.access(candidate, os.X_OK):
            return candidate
    for entry in os.environ.get("PATH", "").split(os.pathsep):
        candidate = Path(entry) / name
        if entry and candidate.is_file() and os.access(candidate, os.X_OK):
            return candidate
    looked = ", ".join(str(p) for p in places)
    raise PlannerNotFoundError(
        f"no `{name}` binary: not in {looked} nor on PATH. Install the package with its "
        "planner (`pip install ./python` from the ebmpc repository builds it; it needs a Rust "
        f"toolchain, https://rustup.rs), or set ${BINARY_ENV} to a planner-service binary "
        "(`cargo build --release` makes target/release/planner-service)"
    )


def default_data_dir() -> Path:
    """Where local planners keep their runs unless told otherwise: ``$EBMPC_DATA_DIR`` if set;
    else the per-user data directory: ``$XDG_DATA_HOME/ebmpc`` (``~/.local/share/ebmpc``) on
    Linux and other Unix systems, ``~/Library/Application Support/ebmpc`` on macOS,
    ``%LOCALAPPDATA%\\ebmpc`` on Windows."""
    explicit = os.environ.get(DATA_DIR_ENV)
    if explicit:
        return Path(explicit)
    home = Path.home()
    if sys.platform == "win32":
        base = os.environ.get("LOCALAPPDATA")
        return (Path(base) if base else home / "AppData" / "Local") / "ebmpc"
    if sys.platform == "darwin":
        return home / "Library" / "Application Support" / "ebmpc"
    xdg = os.environ.get("XDG_DATA_HOME")
    # The XDG spec: a relative value is invalid and is ignored.
    base_dir = Path(xdg) if xdg and os.path.isabs(xdg) else home / ".local" / "share"
    return base_dir / "ebmpc"


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port of ``host`` that was free a moment ago."""
    with socket.socket() as s:
        s.bind((host, 0))
        port: int = s.getsockname()[1]
        return port


def port_is_free(port: int, host: str = "127.0.0.1") -> bool:
    """Whether a TCP listener could bind ``host:port`` now."""
    with socket.socket() as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
        return True


def _daemon_env() -> Dict[str, str]:
    """This process's environment for the daemon, less the ``EBMPC_*`` settings its flags
    would take from it (a user's ``EBMPC_CONNECT`` must not join a local planner to a fleet)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("EBMPC_")}
    env.setdefault("RUST_LOG", "info,zenoh=warn")
    # An error at start is one message, not a backtrace that pushes it out of the log tail.
    env.setdefault("RUST_LIB_BACKTRACE", "0")
    return env


class LocalDaemon:
    """A ``planner-service serve`` process of this machine (see the module's doc).

    ``data_dir``: where its runs live (default :func:`default_data_dir`); ``port``: the
    loopback port to listen on (default: a free one); ``binary``: the planner binary (default
    :func:`find_planner_binary`); ``startup_timeout``: seconds to wait until it serves;
    ``stop_timeout``: seconds :meth:`stop` waits after SIGTERM before it kills the daemon;
    ``extra_args``: more ``serve`` flags. The daemon's log goes to ``data_dir/planner.log``
    (appended to), or to ``log_path``.

    Raises :class:`PlannerNotFoundError`, :class:`PortInUseError`,
    :class:`DataDirLockedError` (another planner serves ``data_dir``) or
    :class:`PlannerStartError` (with the last lines of the daemon's log).
    """

    def __init__(
        self,
        data_dir: Union[os.PathLike[str], str, None] = None,
        *,
        port: Optional[int] = None,
        binary: Union[os.PathLike[str], str, None] = None,
        startup_timeout: float = 60.0,
        stop_timeout: float = 30.0,
        log_path: Union[os.PathLike[str], str, None] = None,
        extra_args: Sequence[str] = (),
    ) -> None:
        self.binary = Path(binary) if binary is not None else find_planner_binary()
        self.data_dir = Path(data_dir) if data_dir is not None else default_data_dir()
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.log_path = Path(log_path) if log_path is not None else self.data_dir / "planner.log"
        self.stop_timeout = stop_timeout
        self.planner_id = LOCAL_PLANNER_ID
        if port is not None and not port_is_free(port):
            raise PortInUseError(
                f"port {port} of 127.0.0.1 is taken: pass another port, or none", ""
            )
        self._extra_args = list(extra_args)
        # A free port can be taken between our look and the daemon's bind: then another one.
        for attempt in range(1 if port is not None else PORT_ATTEMPTS):
            self._start(port if port is not None else free_port())
            try:
                self._wait_until_serving(startup_timeout)
                return
            except PortInUseError:
                self.stop()
                if port is not None or attempt + 1 == PORT_ATTEMPTS:
                    raise
            except BaseException:
                self.stop()
                raise

    def _start(self, port: int) -> None:
        self.port = port
        self.endpoint = f"tcp/127.0.0.1:{port}"
        self._log_start = self.log_path.stat().st_size if self.log_path.exists() else 0
        command = [
            str(self.binary), "serve",
            "--data-dir", str(self.data_dir),
            "--listen", self.endpoint,
            "--planner-id", self.planner_id,
            "--exit-on-stdin-close",
            *self._extra_args,
        ]
        with open(self.log_path, "ab") as log:
            try:
                self.process: subprocess.Popen[bytes] = subprocess.Popen(
                    command,
                    stdin=subprocess.PIPE,
                    stdout=log,
                    stderr=subprocess.STDOUT,
                    env=_daemon_env(),
                    # Its own process group: a Ctrl-C in the terminal reaches only Python,
                    # which then stops the daemon in order (SIGTERM, wait).
                    start_new_session=True,
                )
            except OSError as e:
                raise PlannerStartError(f"cannot run {self.binary}: {e}", "") from None

    def log(self) -> str:
        """What this daemon logged so far."""
        try:
            with open(self.log_path, "rb") as f:
                f.seek(self._log_start)
                return f.read().decode(errors="replace")
        except OSError:
            return ""

    def log_tail(self, lines: int = LOG_TAIL_LINES) -> str:
        """The last ``lines`` lines of :meth:`log`."""
        return "\n".join(self.log().splitlines()[-lines:])

    def _wait_until_serving(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while SERVING_LINE not in self.log():
            status = self.process.poll()
            if status is not None:
                raise self._start_error(f"the planner exited with status {status} at start")
            if time.monotonic() > deadline:
                raise PlannerStartError(
                    f"the planner did not serve within {timeout:g} s (log {self.log_path})",
                    self.log_tail(),
                )
            time.sleep(0.05)

    def _start_error(self, what: str) -> PlannerStartError:
        tail = self.log_tail()
        text = tail.lower()
        if "address already in use" in text or "addrinuse" in text:
            return PortInUseError(f"{what}: port {self.port} is taken", tail)
        if "already serves" in text or "being deleted or archived" in text:
            return DataDirLockedError(
                f"{what}: another planner serves {self.data_dir}; stop it, or give another "
                "data directory", tail,
            )
        return PlannerStartError(f"{what} (log {self.log_path})", tail)

    @property
    def running(self) -> bool:
        """Whether the daemon process is alive."""
        return self.process.poll() is None

    def stop(self) -> Optional[int]:
        """Stops the daemon: SIGTERM, then SIGKILL after ``stop_timeout`` seconds; its exit
        status. Safe to call twice."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(self.stop_timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        if self.process.stdin is not None:
            try:
                self.process.stdin.close()
            except OSError:
                pass
        return self.process.returncode

    def __enter__(self) -> LocalDaemon:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
