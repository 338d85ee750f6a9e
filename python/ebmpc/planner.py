"""The connection to ebmpc planners: attach agents, follow run events, read status."""

from __future__ import annotations

import json
from typing import Any, Dict, List, Mapping, Optional, Sequence, Union

import zenoh

from . import wire
from .agent import Agent
from .errors import NoPlannerError, ProtocolError
from .events import RunEvents

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
        self._session = zenoh.open(config)

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
        """Closes the Zenoh session (agents attached through it go with it)."""
        self._session.close()

    def __enter__(self) -> Planner:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
