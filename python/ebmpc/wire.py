"""The JSON wire format: the protocol version, the key expressions, and the messages this
package sends and reads.

The planner decodes a sample whose Zenoh encoding is ``application/json`` as JSON and answers in
JSON (``proto/src/codec.rs``). The messages' shapes are those of ``proto/src/messages.rs``; their
JSON schemas, generated from the Rust types, ship with this package (``ebmpc/schema/``, see
:func:`schema`), and the protocol version is read from there too, so the package and the planner
it was built with cannot disagree. Keys are those of ``proto/src/keys.rs``.
"""

from __future__ import annotations

import json
from importlib import resources
from typing import Any, Dict, List, Literal, Mapping, Optional, Sequence, Union, cast

from .errors import ProtocolError

#: How an episode ended: the task's termination fired, its time limit, or the agent stopped early.
EpisodeEnd = Literal["terminated", "time_limit", "interrupted"]

#: ``sync``: each episode waits for the models retrained on the last; ``async``: it does not.
TrainMode = Literal["sync", "async"]

#: A task: the name of one in the planner's catalog (``"cartpole"``), or a full task spec (a
#: mapping) for planners that take task specs in the attach message.
Task = Union[str, Mapping[str, Any]]

#: A decoded JSON message.
Message = Dict[str, Any]


def schema(name: str) -> Message:
    """The JSON schema of the wire message ``name`` (``"Observation"``, ``"Action"``, ...,
    ``"PlannerStatus"``), or the index ``"protocol"`` (``protocol_version`` and the names)."""
    text = resources.files("ebmpc").joinpath("schema").joinpath(f"{name}.json").read_text("utf-8")
    return cast(Message, json.loads(text))


#: The protocol version this package speaks: every message carries it.
PROTOCOL_VERSION: int = int(schema("protocol")["protocol_version"])


class Keys:
    """The key expressions of ``proto/src/keys.rs`` under one prefix (default ``ebmpc``)."""

    def __init__(self, prefix: str = "ebmpc") -> None:
        self.prefix = prefix.strip("/")

    def attach(self, run: str) -> str:
        return f"{self.prefix}/runs/{run}/attach"

    def agent(self, run: str, agent: str, channel: Literal["obs", "act", "error"]) -> str:
        return f"{self.prefix}/runs/{run}/agents/{agent}/{channel}"

    def events_json(self, run: str) -> str:
        """A run's events in JSON (the planner publishes them in postcard on ``…/events``)."""
        return f"{self.prefix}/runs/{run}/events/json"

    def planner_status(self, planner: str) -> str:
        return f"{self.prefix}/planners/{planner}/status"

    def agent_alive(self, run: str, agent: str) -> str:
        return f"{self.prefix}/alive/runs/{run}/agents/{agent}"


def _takes_task_specs() -> bool:
    """Whether this protocol's attach carries whole task specs (``RunSpec.task_spec``)."""
    run_spec = schema("AttachRequest").get("$defs", {}).get("RunSpec", {})
    return "task_spec" in run_spec.get("properties", {})


#: Whether planners of this protocol version take a task spec in the attach message (read from
#: the shipped schema, so it follows the planner this package was generated with).
TAKES_TASK_SPECS: bool = _takes_task_specs()


def task_fields(task: Task) -> Message:
    """The attach request's task fields: ``task``, the task's name; and ``task_spec``, the whole
    spec, when ``task`` is a mapping (its ``name`` is the task's name).

    The one place that encodes a task. A protocol without task specs gets a :class:`ValueError`
    for a mapping: its planners would ignore the spec and plan for a catalog task of that name.
    """
    if isinstance(task, str):
        return {"task": task}
    if not TAKES_TASK_SPECS:
        raise ValueError(
            f"planners of protocol {PROTOCOL_VERSION} take catalog task names only, not task specs"
        )
    spec = dict(task)
    name = spec.get("name")
    if not isinstance(name, str):
        raise ValueError("a task spec needs its `name`")
    return {"task": name, "task_spec": spec}


def attach_request(
    agent: str,
    task: Task,
    preset: Optional[str],
    overrides: Optional[Mapping[str, Any]],
    mode: TrainMode,
    seed: int,
    session: Optional[int],
) -> Message:
    """An ``AttachRequest``. ``session``: the agent's claim to its name, the token of its
    current session when it attaches again (the planner then replaces that session even while
    it is live), or on a first attach a token it drew, so that asking again for a lost answer
    is accepted as the same agent."""
    request: Message = {
        "version": PROTOCOL_VERSION,
        "agent": agent,
        "spec": {
            **task_fields(task),
            "preset": preset,
            "overrides": dict(overrides or {}),
            "mode": mode,
            "seed": seed,
        },
    }
    if session:
        request["session"] = session
    return request


def observation(
    episode: int,
    step: int,
    obs: Sequence[float],
    session: int,
    reward: Optional[float] = None,
    end: Optional[EpisodeEnd] = None,
    applied: Optional[Sequence[float]] = None,
) -> Message:
    """An ``Observation``: step 0 starts an episode (no reward); step ``t > 0`` is the result of
    the action for step ``t - 1`` with that transition's reward; ``end`` marks the last."""
    message: Message = {
        "version": PROTOCOL_VERSION,
        "episode": episode,
        "step": step,
        "obs": [float(x) for x in obs],
        "session": session,
    }
    if reward is not None:
        message["reward"] = float(reward)
    if end is not None:
        message["end"] = end
    if applied is not None:
        message["applied"] = [float(x) for x in applied]
    return message


def encode(message: Mapping[str, Any]) -> bytes:
    """JSON bytes of a message. JSON has no NaN or infinity: a non-finite number raises
    :class:`ValueError` here, before anything is sent."""
    try:
        return json.dumps(message, allow_nan=False).encode()
    except ValueError as e:
        raise ValueError(f"cannot send a non-finite number: {e}") from None


def decode(payload: bytes, what: str) -> Message:
    """A received message of the current protocol version, or :class:`ProtocolError`."""
    try:
        message = json.loads(payload)
    except ValueError as e:
        raise ProtocolError(f"undecodable {what}: {e}") from None
    if not isinstance(message, dict):
        raise ProtocolError(f"{what} is not a JSON object: {payload[:80]!r}")
    version = message.get("version")
    if version != PROTOCOL_VERSION:
        raise ProtocolError(
            f"{what} of protocol version {version!r}; this package speaks {PROTOCOL_VERSION}"
        )
    return message


def float_list(value: Any, what: str) -> List[float]:
    """A list of numbers from a decoded message, or :class:`ProtocolError`."""
    if not isinstance(value, list) or not all(isinstance(x, (int, float)) for x in value):
        raise ProtocolError(f"{what} is not a list of numbers: {value!r}")
    return [float(x) for x in value]
