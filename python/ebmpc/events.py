"""Run events: what happens to a run (episodes stored, training, new models), as typed values.

The planner publishes every event of a run in JSON on ``{prefix}/runs/{run}/events/json``;
:class:`RunEvents` subscribes there and iterates over them.
"""

from __future__ import annotations

import queue
from dataclasses import dataclass
from typing import Any, Iterator, Mapping, Optional, Union

import zenoh

from . import wire
from .errors import EventTimeout, ProtocolError


@dataclass(frozen=True)
class EpisodeFinished:
    """An agent finished an episode and the planner stored its transitions."""

    run: str
    agent: str
    episode: int
    #: The sum of the rewards the agent sent.
    episode_return: float
    steps: int
    end: wire.EpisodeEnd


@dataclass(frozen=True)
class TrainingStarted:
    """The trainer started retraining on ``transitions`` stored transitions."""

    run: str
    transitions: int


@dataclass(frozen=True)
class ModelsUpdated:
    """New models are in use."""

    run: str
    models_version: int
    dynamics_loss: float
    energy_loss: float
    seconds: float
    #: The reward model's loss, for a task whose reward is learned (else ``None``).
    reward_loss: Optional[float] = None
    #: A learned termination's accuracy on the transitions held out of its training (else
    #: ``None``, also before any episode ended as ``terminated``).
    termination_accuracy: Optional["TerminationAccuracy"] = None


@dataclass(frozen=True)
class TerminationAccuracy:
    """How well a learned termination predicts episode ends it was not trained on."""

    #: Held-out transitions it was scored on, and how many of them ended their episode.
    held_out: int
    terminations: int
    #: Fraction of them classified right, and of their ends predicted (1 with none).
    accuracy: float
    recall: float


@dataclass(frozen=True)
class TrainingFailed:
    """A retraining failed; the previous models stay in use."""

    run: str
    message: str


#: One run event.
RunEvent = Union[EpisodeFinished, TrainingStarted, ModelsUpdated, TrainingFailed]


def parse_event(message: Mapping[str, Any]) -> RunEvent:
    """The event of a decoded ``RunEvent`` message, or :class:`ProtocolError`."""
    run = message.get("run")
    kind = message.get("kind")
    if not isinstance(run, str) or not isinstance(kind, dict) or len(kind) != 1:
        raise ProtocolError(f"not a run event: {dict(message)!r}")
    ((name, fields),) = kind.items()
    try:
        if name == "EpisodeFinished":
            end = fields["end"]
            if end not in ("terminated", "time_limit", "interrupted"):
                raise ValueError("end")
            return EpisodeFinished(
                run,
                str(fields["agent"]),
                int(fields["episode"]),
                float(fields["episode_return"]),
                int(fields["steps"]),
                end,
            )
        if name == "TrainingStarted":
            return TrainingStarted(run, int(fields["transitions"]))
        if name == "ModelsUpdated":
            return ModelsUpdated(
                run,
                int(fields["models_version"]),
                float(fields["dynamics_loss"]),
                float(fields["energy_loss"]),
                float(fields["seconds"]),
                None if fields.get("reward_loss") is None else float(fields["reward_loss"]),
                _termination_accuracy(fields.get("termination_accuracy")),
            )
        if name == "TrainingFailed":
            return TrainingFailed(run, str(fields["message"]))
    except (KeyError, TypeError, ValueError) as e:
        raise ProtocolError(f"run event {name} without a valid {e}: {fields!r}") from None
    raise ProtocolError(f"unknown run event kind `{name}`")


def _termination_accuracy(fields: Any) -> Optional[TerminationAccuracy]:
    if fields is None:
        return None
    return TerminationAccuracy(
        int(fields["held_out"]), int(fields["terminations"]),
        float(fields["accuracy"]), float(fields["recall"]),
    )


class RunEvents(Iterator[RunEvent]):
    """The events of one run, in the order they arrive, from the moment of subscribing.

    Iterating blocks until the next event; with a ``timeout`` (seconds), a wait longer than it
    raises :class:`EventTimeout`. Close it (or use it as a context manager) to unsubscribe.
    """

    def __init__(self, session: zenoh.Session, keys: wire.Keys, run: str,
                 timeout: Optional[float] = None) -> None:
        self.run = run
        self.timeout = timeout
        self._inbox: queue.Queue[Union[RunEvent, ProtocolError]] = queue.Queue()
        self._subscriber = session.declare_subscriber(keys.events_json(run), self._receive)

    def _receive(self, sample: zenoh.Sample) -> None:
        try:
            event: Union[RunEvent, ProtocolError] = parse_event(
                wire.decode(sample.payload.to_bytes(), "run event")
            )
        except ProtocolError as e:
            event = e
        self._inbox.put(event)

    def next(self, timeout: Optional[float] = None) -> RunEvent:
        """The next event, waiting at most ``timeout`` seconds (``None``: the iterator's)."""
        wait = self.timeout if timeout is None else timeout
        try:
            event = self._inbox.get(timeout=wait)
        except queue.Empty:
            raise EventTimeout(f"no event of run `{self.run}` within {wait} s") from None
        if isinstance(event, ProtocolError):
            raise event
        return event

    def __next__(self) -> RunEvent:
        return self.next()

    def __iter__(self) -> RunEvents:
        return self

    def close(self) -> None:
        """Unsubscribes; events published afterwards are not received."""
        self._subscriber.undeclare()

    def __enter__(self) -> RunEvents:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
