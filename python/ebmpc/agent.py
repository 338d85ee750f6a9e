"""One agent of one run: its episodes, step by step.

An :class:`Agent` (made by :meth:`ebmpc.Planner.attach`) keeps what the protocol asks of a
controller so that its user does not have to: the episode and step numbers, the session token
of its attach on every observation, the run's ownership epoch (actions of an older epoch come
from a planner that lost the run, and are ignored), and sending a step again after the planner
reported that it could not store it (``storage``: nothing of it was kept, the session did not
move on).
"""

from __future__ import annotations

import logging
import queue
import secrets
import time
from typing import Any, List, Mapping, Optional, Sequence, Tuple

import zenoh

from . import wire
from .errors import (
    ActionTimeout,
    EventTimeout,
    NoPlannerError,
    PlannerError,
    ProtocolError,
    StorageError,
    from_report,
)
from .events import EpisodeFinished, RunEvents

log = logging.getLogger("ebmpc")

#: Pause before sending again an observation the planner could not store (its disk is full).
STORAGE_RETRY_PAUSE = 1.0


class Agent:
    """An agent attached to a run. Use :meth:`act` for every step and :meth:`end` for the last
    one of an episode; :meth:`close` (or a ``with`` block) detaches it.

    Attributes set by the attach: ``planner_id``, ``task``, ``mode``, ``models_version`` (of the
    last action, or of the attach), ``episode`` (the episode in progress, or the next one),
    ``episodes_done``, ``epoch`` and ``session`` (the session token). ``last_stats`` holds the plan statistics of
    the last action (``source``, ``planning_ms``, ``iterations``, ...).
    """

    def __init__(
        self,
        session: zenoh.Session,
        keys: wire.Keys,
        run: str,
        name: str,
        action_timeout: float,
        train_timeout: float,
    ) -> None:
        self.run = run
        self.name = name
        self.action_timeout = action_timeout
        self.train_timeout = train_timeout
        self._session = session
        self._keys = keys
        self.session = 0
        # The token the first attach presents: asking again after an answer that never
        # arrived (the query timed out), this agent proves it is the one the planner attached.
        self._first_claim = secrets.randbits(64) or 1
        self.epoch = 0
        self.planner_id = ""
        self.task: Any = None
        self.mode = "sync"
        self.models_version = 0
        self.episode = 0
        self.episodes_done = 0  # finished episodes of the run (all its agents) at the attach
        self.step: Optional[int] = None  # the last step sent in the episode in progress
        self.last_stats: Mapping[str, Any] = {}
        self._last_sent: Optional[bytes] = None
        # (the step before, the step) of an observation submitted whose action is not collected.
        self._pending: Optional[Tuple[Optional[int], int]] = None
        self._inbox: queue.Queue[Tuple[str, Any]] = queue.Queue()
        # Everything is declared before attaching, so no answer can arrive before we listen.
        self._token = session.liveliness().declare_token(keys.agent_alive(run, name))
        self._subscribers = [
            session.declare_subscriber(keys.agent(run, name, "act"), self._receiver("act")),
            session.declare_subscriber(keys.agent(run, name, "error"), self._receiver("error")),
        ]
        self._events = RunEvents(session, keys, run)
        self._publisher = session.declare_publisher(
            keys.agent(run, name, "obs"),
            encoding=zenoh.Encoding.APPLICATION_JSON,
            # A control loop must not lose an observation to a full queue: block instead.
            congestion_control=zenoh.CongestionControl.BLOCK,
            express=True,
        )

    def _receiver(self, channel: str) -> Any:
        what = "action" if channel == "act" else "error report"

        def receive(sample: zenoh.Sample) -> None:
            # The attach reply checked that the planner speaks our protocol, so a message that
            # does not decode is a stray or hostile publisher's: raising it would let anyone on
            # the network stop this agent. It is logged and skipped; a planner that truly sends
            # nothing usable ends the wait with the action timeout.
            try:
                message = wire.decode(sample.payload.to_bytes(), what)
            except ProtocolError as e:
                log.warning("ignoring an undecodable %s on %s: %s", what, sample.key_expr, e)
                return
            if channel == "error" and message.get("session") not in (None, self.session):
                return  # a refusal of another process's observation under our name
            self._inbox.put((channel, message))

        return receive

    # ----------------------------------------------------------------------------------------
    # Attaching.
    # ----------------------------------------------------------------------------------------

    def _attach(
        self,
        task: wire.Task,
        preset: Optional[str],
        overrides: Optional[Mapping[str, Any]],
        mode: wire.TrainMode,
        seed: int,
        patience: float,
    ) -> None:
        """Queries the run's attach key until a planner answers (raising its refusal)."""
        key = self._keys.attach(self.run)
        request = wire.attach_request(
            self.name, task, preset, overrides, mode, seed, self.session or self._first_claim
        )
        payload = wire.encode(request)
        deadline = time.monotonic() + patience
        failure = None
        while True:
            wait = max(0.5, min(5.0, deadline - time.monotonic()))
            # Every planner gets the query; only the run's owner answers.
            for reply in self._session.get(
                key,
                payload=payload,
                encoding=zenoh.Encoding.APPLICATION_JSON,
                timeout=wait,
                target=zenoh.QueryTarget.ALL,
                consolidation=zenoh.ConsolidationMode.NONE,
            ):
                if reply.ok is None:
                    # zenoh's own error (the query timed out while a planner was still
                    # loading the run, say): planners refuse inside an attach reply. Ask again.
                    failure = reply.err.payload.to_string() if reply.err else "no reason given"
                    continue
                answer = wire.decode(reply.ok.payload.to_bytes(), "attach reply")
                outcome = answer.get("outcome")
                if not isinstance(outcome, dict):
                    raise ProtocolError(f"attach reply without an outcome: {answer!r}")
                if "Rejected" in outcome:
                    raise from_report(outcome["Rejected"])
                self._accept(outcome.get("Accepted"))
                self._wait_until_planner_listens(deadline)
                return
            if time.monotonic() + 0.5 >= deadline:
                last = f"; the last query ended in: {failure}" if failure else ""
                raise NoPlannerError(
                    f"no planner answered on `{key}` within {patience:g} s{last}"
                )
            time.sleep(0.5)

    def _accept(self, accepted: Any) -> None:
        if not isinstance(accepted, dict) or not isinstance(accepted.get("session"), int):
            raise ProtocolError(f"attach accepted without a session: {accepted!r}")
        self.session = accepted["session"]
        self.epoch = int(accepted.get("epoch", 0))
        self.planner_id = str(accepted.get("planner_id"))
        self.task = accepted.get("task")
        self.mode = str(accepted.get("mode"))
        self.models_version = int(accepted.get("models_version", 0))
        self.episode = int(accepted.get("next_episode", 0))
        self.episodes_done = int(accepted.get("episodes_done", 0))
        self.step = None

    def _wait_until_planner_listens(self, deadline: float) -> None:
        """The first observation must not be published before the planner's subscriber is known."""
        while not self._publisher.matching_status:
            if time.monotonic() >= deadline:
                raise NoPlannerError("the planner never subscribed to our observations")
            time.sleep(0.05)

    # ----------------------------------------------------------------------------------------
    # Acting.
    # ----------------------------------------------------------------------------------------

    @property
    def in_episode(self) -> bool:
        """Whether an episode is in progress (its first step was sent and no end yet)."""
        return self.step is not None

    def act(
        self,
        obs: Sequence[float],
        reward: Optional[float] = None,
        applied: Optional[Sequence[float]] = None,
        timeout: Optional[float] = None,
    ) -> List[float]:
        """Sends an observation and returns the planner's action for it.

        The first call of an episode starts it (step 0: no ``reward``); every later call is the
        next step, with the ``reward`` of the transition into ``obs`` (required). ``applied``:
        the action actually applied at the previous step, when it differs from the one returned
        (clipped by the robot, overridden by a safety layer); the planner learns from that one.
        ``timeout``: seconds to wait for the action (default: ``train_timeout`` at step 0,
        where sync mode waits for retraining, ``action_timeout`` after).

        :meth:`submit` and :meth:`result` are its two halves, for a caller that sends several
        agents' observations before it waits for their actions (a vector environment).
        """
        self.submit(obs, reward, applied)
        return self.result(timeout)

    def submit(
        self,
        obs: Sequence[float],
        reward: Optional[float] = None,
        applied: Optional[Sequence[float]] = None,
    ) -> None:
        """Sends an observation as :meth:`act` does, without waiting for its action: collect
        that with :meth:`result` before the next :meth:`submit` or :meth:`end`."""
        if self._pending is not None:
            raise ValueError("the last observation's action was not collected: call result()")
        if self.step is None:
            if reward is not None or applied is not None:
                raise ValueError("the first step of an episode has no reward and no applied action")
            step = 0
        else:
            if reward is None:
                raise ValueError("every step after the first needs the reward of the last action")
            step = self.step + 1
        self._send(wire.observation(self.episode, step, obs, self.session, reward, None, applied))
        self._pending = (self.step, step)
        self.step = step

    def result(self, timeout: Optional[float] = None) -> List[float]:
        """The planner's action for the observation of the last :meth:`submit` (``timeout``
        as in :meth:`act`)."""
        if self._pending is None:
            raise ValueError("no observation awaits its action: call submit() first")
        previous, step = self._pending
        wait = timeout if timeout is not None else (
            self.train_timeout if step == 0 else self.action_timeout
        )
        try:
            action = self._action(self.episode, step, wait)
        except PlannerError:
            # The planner used nothing of a refused observation: the step can be sent again.
            self.step = previous
            raise
        finally:
            self._pending = None
        return action

    def end(
        self,
        obs: Sequence[float],
        reward: float,
        kind: wire.EpisodeEnd = "time_limit",
        applied: Optional[Sequence[float]] = None,
        wait: bool = True,
        timeout: Optional[float] = None,
    ) -> Optional[EpisodeFinished]:
        """Ends the episode in progress with its last observation (which gets no action): the
        result of the last action, its ``reward``, and why it ended (``kind``: ``terminated``,
        ``time_limit`` or ``interrupted``).

        With ``wait`` (the default) it returns once the planner stored the episode: its
        :class:`EpisodeFinished` event, whose return the planner summed from the rewards sent
        (raising the planner's error if it refused the last step). The next :meth:`act` starts
        the next episode.
        """
        if self.step is None:
            raise ValueError("no episode in progress: call act() for its first step")
        if self._pending is not None:
            raise ValueError("the last observation's action was not collected: call result()")
        episode, step = self.episode, self.step + 1
        self._send(wire.observation(episode, step, obs, self.session, reward, kind, applied))
        self.step = None
        self.episode += 1
        if not wait:
            return None
        return self._stored(episode, self.action_timeout if timeout is None else timeout)

    def _send(self, message: Mapping[str, Any]) -> None:
        payload = wire.encode(message)
        self._last_sent = payload
        self._publisher.put(payload)

    def _report(self, report: Mapping[str, Any], deadline: float) -> None:
        """Raises the planner's error report, unless it is ``storage`` with time left to send the
        step again (as sim-bridge does): then it is sent again after a pause."""
        error = from_report(report)
        if isinstance(error, StorageError) and self._last_sent is not None:
            if time.monotonic() + STORAGE_RETRY_PAUSE < deadline:
                log.warning("the planner could not store a step, sending it again: %s", error)
                time.sleep(STORAGE_RETRY_PAUSE)
                self._publisher.put(self._last_sent)
                return
        raise error

    def _next_message(self, deadline: float) -> Optional[Tuple[str, Any]]:
        try:
            return self._inbox.get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            return None

    def _action(self, episode: int, step: int, timeout: float) -> List[float]:
        deadline = time.monotonic() + timeout
        while True:
            received = self._next_message(deadline)
            if received is None:
                raise ActionTimeout(
                    f"no action for episode {episode} step {step} within {timeout:g} s"
                )
            channel, message = received
            if channel == "error":
                self._report(message, deadline)
                continue
            if int(message.get("epoch", 0)) < self.epoch:
                log.info("ignoring an action of stale epoch %s", message.get("epoch"))
                continue
            if (message.get("episode"), message.get("step")) != (episode, step):
                # An answer to an earlier step cannot come after its successor's question was
                # asked; anything else is not ours to act on.
                log.info("ignoring an action for %s/%s", message.get("episode"), message.get("step"))
                continue
            self.epoch = int(message.get("epoch", 0))
            stats = message.get("stats")
            self.last_stats = stats if isinstance(stats, dict) else {}
            self.models_version = int(self.last_stats.get("models_version", self.models_version))
            return wire.float_list(message.get("action"), "action")

    def _stored(self, episode: int, timeout: float) -> EpisodeFinished:
        """Waits for the planner's event saying that `episode` of this agent is stored, raising
        any error report about our session that arrives meanwhile."""
        deadline = time.monotonic() + timeout
        while True:
            received: Optional[Tuple[str, Any]] = None
            try:
                received = self._inbox.get_nowait()
            except queue.Empty:
                pass
            if received is not None:
                channel, message = received
                if channel == "error":
                    self._report(message, deadline)
                continue  # a late action of an earlier step: nothing to act on
            try:
                event = self._events.next(timeout=min(0.1, max(0.0, deadline - time.monotonic())))
            except EventTimeout:
                if time.monotonic() >= deadline:
                    raise EventTimeout(
                        f"the planner did not report episode {episode} as stored "
                        f"within {timeout:g} s"
                    ) from None
                continue
            if (
                isinstance(event, EpisodeFinished)
                and event.agent == self.name
                and event.episode == episode
            ):
                return event

    # ----------------------------------------------------------------------------------------

    def close(self) -> None:
        """Detaches: the planner sees this agent go (its liveliness token) and frees the name."""
        self._events.close()
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._publisher.undeclare()
        self._token.undeclare()

    def __enter__(self) -> Agent:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

