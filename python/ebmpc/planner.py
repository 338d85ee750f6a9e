"""The connection to ebmpc planners: attach agents, follow run events, read status."""

from __future__ import annotations

import json
import os
import time
from typing import Any, Dict, List, Mapping, Optional, Sequence, Union

import zenoh

from . import wire
from .agent import Agent
from .errors import NoPlannerError, PlannerStartError, ProtocolError
from .events import RunEvents
from .local import LocalDaemon

#: Where a planner listens when nothing else is said (``planner-service serve``'s default).
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


class Planner:
    """A Zenoh session to one planner, or to a router in front of a fleet of them.

    ``connect``: the endpoint(s) to connect to (``"tcp/127.0.0.1:7447"``, default that unless
    ``zenoh_config`` is given); ``zenoh_config``: a Zenoh JSON5 config file to start from (TLS, a
    client mode); multicast scouting is always off, as in every ebmpc process. ``prefix``: the
    key prefix shared with the planner. The timeouts (seconds) are the defaults of the agents it
    attaches: ``attach_timeout`` to find the run's planner, ``action_timeout`` for an action,
    ``train_timeout`` for an episode's first action (sync mode waits there for retraining).
    """

    def __init__(
        self,
        connect: Union[str, Sequence[str], None] = None,
        *,
        zenoh_config: Optional[str] = None,
        prefix: str = "ebmpc",
        attach_timeout: float = 60.0,
        action_timeout: float = 60.0,
        train_timeout: float = 600.0,
    ) -> None:
        endpoints = [connect] if isinstance(connect, str) else list(connect or [])
        if not endpoints and zenoh_config is None:
            endpoints = [DEFAULT_ENDPOINT]
        config = zenoh.Config.from_file(zenoh_config) if zenoh_config else zenoh.Config()
        config.insert_json5("scouting/multicast/enabled", "false")
        if endpoints:
            config.insert_json5("connect/endpoints", json.dumps(endpoints))
        self.keys = wire.Keys(prefix)
        self.attach_timeout = attach_timeout
        self.action_timeout = action_timeout
        self.train_timeout = train_timeout
        #: The daemon this planner started (:meth:`local`), stopped by :meth:`close`.
        self.daemon: Optional[LocalDaemon] = None
        self._session = zenoh.open(config)

    @classmethod
    def local(
        cls,
        data_dir: Union[str, "os.PathLike[str]", None] = None,
        *,
        port: Optional[int] = None,
        binary: Union[str, "os.PathLike[str]", None] = None,
        startup_timeout: float = 60.0,
        stop_timeout: float = 30.0,
        attach_timeout: float = 60.0,
        action_timeout: float = 60.0,
        train_timeout: float = 600.0,
    ) -> Planner:
        """A planner daemon of this machine, started for this Python process, and a session
        to it: the ``planner-service`` installed with this package (or ``binary``) serving
        ``data_dir`` (default :func:`ebmpc.local.default_data_dir`, the per-user data
        directory, so a later start resumes the runs) on a free loopback port (or ``port``),
        multicast scouting off. It returns once the daemon answers a status query.

        :meth:`close` (or the end of a ``with`` block) stops it (SIGTERM, then SIGKILL after
        ``stop_timeout`` seconds); it also stops by itself when this process ends in any way,
        SIGKILL included. Raises :class:`~ebmpc.PlannerNotFoundError`,
        :class:`~ebmpc.PortInUseError`, :class:`~ebmpc.DataDirLockedError` (another planner
        serves ``data_dir``) or :class:`~ebmpc.PlannerStartError` (it exited at start: the
        last lines of its log are in the message). The timeouts are :class:`Planner`'s.
        """
        daemon = LocalDaemon(
            data_dir,
            port=port,
            binary=binary,
            startup_timeout=startup_timeout,
            stop_timeout=stop_timeout,
        )
        planner: Optional[Planner] = None
        try:
            planner = cls(
                daemon.endpoint,
                attach_timeout=attach_timeout,
                action_timeout=action_timeout,
                train_timeout=train_timeout,
            )
            planner.daemon = daemon
            planner._wait_until_answering(startup_timeout)
        except BaseException:
            if planner is not None:
                planner.close()  # stops the daemon too
            else:
                daemon.stop()
            raise
        return planner

    def _wait_until_answering(self, timeout: float) -> None:
        """Asks the local daemon for its status until it answers (the session may still be
        connecting), raising its start error if it exits meanwhile."""
        assert self.daemon is not None
        deadline = time.monotonic() + timeout
        while True:
            if not self.daemon.running:
                raise self.daemon._start_error(
                    f"the planner exited with status {self.daemon.process.returncode} at start"
                )
            try:
                self.status(self.daemon.planner_id, timeout=1.0)
                return
            except NoPlannerError:
                if time.monotonic() > deadline:
                    raise PlannerStartError(
                        f"the local planner did not answer within {timeout:g} s",
                        self.daemon.log_tail(),
                    ) from None

    def attach(
        self,
        run: str,
        task: wire.Task,
        preset: Optional[str] = None,
        overrides: Optional[Mapping[str, Any]] = None,
        *,
        agent: str = "python-0",
        mode: wire.TrainMode = "sync",
        seed: int = 0,
        timeout: Optional[float] = None,
    ) -> Agent:
        """Attaches agent ``agent`` to ``run``, creating the run if it is new.

        ``task``: a task of the planner's catalog by name, or a whole task spec (a mapping with
        its ``name``) where the protocol takes one (see :func:`ebmpc.wire.task_fields`). ``preset``: the planner preset (``cem+deen`` by default on
        the planner's side); ``overrides``: preset fields to change (``{"population": 100}``).
        The first agent's spec (task, preset, overrides, mode, seed) is the run's; a later one
        that differs is refused. Raises the planner's refusal as its :class:`PlannerError`
        subclass, and :class:`NoPlannerError` when no planner answers within ``timeout``
        (default ``attach_timeout``).
        """
        handle = Agent(
            self._session, self.keys, run, agent, self.action_timeout, self.train_timeout
        )
        try:
            patience = self.attach_timeout if timeout is None else timeout
            handle._attach(task, preset, overrides, mode, seed, patience)
        except BaseException:
            handle.close()
            raise
        return handle

    def events(self, run: str, timeout: Optional[float] = None) -> RunEvents:
        """The events of ``run`` from now on, as an iterator (see :class:`RunEvents`)."""
        return RunEvents(self._session, self.keys, run, timeout)

    def status(self, planner: str = "*", timeout: float = 5.0) -> List[Dict[str, Any]]:
        """The status reports (JSON objects: runs, agents, episodes, latencies, ...) of every
        planner that answers within ``timeout``, or of the planner with id ``planner``; sorted
        by planner id. Raises :class:`NoPlannerError` when none answers."""
        reports: List[Dict[str, Any]] = []
        for reply in self._session.get(
            self.keys.planner_status(planner),
            timeout=timeout,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
        ):
            if reply.ok is None:
                continue
            try:
                report = json.loads(reply.ok.payload.to_bytes())
            except ValueError as e:
                raise ProtocolError(f"undecodable status report: {e}") from None
            if isinstance(report, dict):
                reports.append(report)
        if not reports:
            raise NoPlannerError(f"no planner `{planner}` answered a status query within {timeout:g} s")
        return sorted(reports, key=lambda r: str(r.get("planner_id")))

    def close(self) -> None:
        """Closes the Zenoh session (agents attached through it go with it), and stops the
        daemon of :meth:`local`."""
        try:
            self._session.close()
        finally:
            if self.daemon is not None:
                self.daemon.stop()

    def __enter__(self) -> Planner:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
