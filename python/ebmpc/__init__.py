"""Python client of the ebmpc planning service.

A planner learns to control a system from the experience its agents send; an agent asks it for
an action at every step::

    from ebmpc import Planner

    with Planner.local() as planner:                  # or Planner(connect="tcp/host:7447")
        agent = planner.attach("my-run", "cartpole", overrides={"population": 100})
        obs = env.reset()
        action = agent.act(obs)                       # the first step of an episode
        for t in range(199):
            obs, reward = env.step(action)
            action = agent.act(obs, reward)
        obs, reward = env.step(action)
        agent.end(obs, reward, "time_limit")          # stored: the planner retrains

``Planner.local()`` starts the ``planner-service`` installed with this package on a free loopback
port (runs under :func:`ebmpc.local.default_data_dir`) and stops it with the ``with`` block.
Errors the planner reports raise the :class:`PlannerError` subclass of their code.
"""

from .agent import Agent
from .errors import (
    ActionTimeout,
    DataDirLockedError,
    DimensionError,
    EbmpcError,
    EventTimeout,
    InternalError,
    MalformedError,
    NoPlannerError,
    NonFiniteError,
    NotAttachedError,
    OutOfOrderError,
    OutOfRangeError,
    PlannerError,
    PlannerNotFoundError,
    PlannerStartError,
    PortInUseError,
    ProtocolError,
    ProtocolVersionError,
    RefusedError,
    SessionError,
    StorageError,
    UnknownRunError,
    UnknownTaskError,
)
from .events import (
    EpisodeFinished,
    ModelsUpdated,
    RunEvent,
    RunEvents,
    TerminationAccuracy,
    TrainingFailed,
    TrainingStarted,
)
from .planner import Planner
from .wire import PROTOCOL_VERSION, EpisodeEnd, Task, TrainMode

__all__ = [
    "PROTOCOL_VERSION",
    "ActionTimeout",
    "Agent",
    "DataDirLockedError",
    "DimensionError",
    "EbmpcError",
    "EpisodeEnd",
    "EpisodeFinished",
    "EventTimeout",
    "InternalError",
    "MalformedError",
    "ModelsUpdated",
    "NoPlannerError",
    "NonFiniteError",
    "NotAttachedError",
    "OutOfOrderError",
    "OutOfRangeError",
    "Planner",
    "PlannerError",
    "PlannerNotFoundError",
    "PlannerStartError",
    "PortInUseError",
    "ProtocolError",
    "ProtocolVersionError",
    "RefusedError",
    "RunEvent",
    "RunEvents",
    "SessionError",
    "StorageError",
    "Task",
    "TerminationAccuracy",
    "TrainMode",
    "TrainingFailed",
    "TrainingStarted",
    "UnknownRunError",
    "UnknownTaskError",
]
