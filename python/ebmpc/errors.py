"""The exceptions of the ebmpc client.

Every error the planner reports (an ``ErrorReport`` on the wire) raises the subclass of
:class:`PlannerError` named after its code, carrying the planner's code and message, so a caller
can catch exactly what it can handle (``except ebmpc.StorageError``) and let the rest through.
Failures on this side (no planner answered, no action in time, an answer that is not a message)
raise the other subclasses of :class:`EbmpcError`.
"""

from __future__ import annotations

from typing import Any, ClassVar, Dict, Mapping, Optional, Type


class EbmpcError(Exception):
    """Base class of every exception this package raises."""


class PlannerError(EbmpcError):
    """An error report from the planner: ``code`` (the wire's ``ErrorCode``, e.g. ``"refused"``),
    its ``message``, and the episode and step of the offending message when known.

    Raised as the subclass of its code; as this class itself only for a code this package does
    not know (a newer planner).
    """

    #: The wire code of the subclass (empty on this base class).
    CODE: ClassVar[str] = ""

    def __init__(
        self,
        code: str,
        message: str,
        episode: Optional[int] = None,
        step: Optional[int] = None,
        session: Optional[int] = None,
    ) -> None:
        self.code = code
        self.message = message
        self.episode = episode
        self.step = step
        self.session = session
        where = f" (episode {episode}, step {step})" if episode is not None else ""
        super().__init__(f"{code}: {message}{where}")


class MalformedError(PlannerError):
    """The planner could not decode what was sent."""

    CODE = "malformed"


class ProtocolVersionError(PlannerError):
    """This package speaks another protocol version than the planner."""

    CODE = "protocol_version"


class DimensionError(PlannerError):
    """A vector had the wrong length for the task."""

    CODE = "dimension"


class NonFiniteError(PlannerError):
    """A NaN or infinity where a finite number is required."""

    CODE = "non_finite"


class UnknownRunError(PlannerError):
    """The run does not exist on the planner."""

    CODE = "unknown_run"


class UnknownTaskError(PlannerError):
    """The task is not in the planner's catalog."""

    CODE = "unknown_task"


class NotAttachedError(PlannerError):
    """The agent is not attached (also when its run moved to another planner): attach again."""

    CODE = "not_attached"


class OutOfOrderError(PlannerError):
    """Episode or step numbering did not follow on from the previous message."""

    CODE = "out_of_order"


class RefusedError(PlannerError):
    """The planner refuses: a limit, a spec that differs from the run's, an invalid name."""

    CODE = "refused"


class InternalError(PlannerError):
    """Something failed inside the planner."""

    CODE = "internal"


class OutOfRangeError(PlannerError):
    """A finite number beyond its bound (the task's magnitudes, or the action bounds)."""

    CODE = "out_of_range"


class StorageError(PlannerError):
    """The planner could not store the step (its disk is full); nothing of it was kept.

    :class:`ebmpc.Agent` sends the step again by itself until its timeout; this is raised only
    when the planner still could not store it by then.
    """

    CODE = "storage"


class SessionError(PlannerError):
    """The observation's session token is not the agent's current one: attach again."""

    CODE = "session"


#: The exception class of each wire error code.
ERROR_CLASSES: Dict[str, Type[PlannerError]] = {
    cls.CODE: cls
    for cls in (
        MalformedError,
        ProtocolVersionError,
        DimensionError,
        NonFiniteError,
        UnknownRunError,
        UnknownTaskError,
        NotAttachedError,
        OutOfOrderError,
        RefusedError,
        InternalError,
        OutOfRangeError,
        StorageError,
        SessionError,
    )
}


def from_report(report: Mapping[str, Any]) -> PlannerError:
    """The exception of a decoded ``ErrorReport``."""
    code = str(report.get("code"))
    cls = ERROR_CLASSES.get(code, PlannerError)
    return cls(
        code,
        str(report.get("message")),
        episode=report.get("episode"),
        step=report.get("step"),
        session=report.get("session"),
    )


class NoPlannerError(EbmpcError):
    """No planner answered an attach or a status query in time."""


class ActionTimeout(EbmpcError, TimeoutError):
    """The planner's action for a step did not arrive in time."""


class EventTimeout(EbmpcError, TimeoutError):
    """No run event arrived in time."""


class ProtocolError(EbmpcError):
    """Something arrived from the planner that is not a valid message of this protocol."""


class PlannerNotFoundError(EbmpcError):
    """No ``planner-service`` binary to start a local planner with (see
    :func:`ebmpc.local.find_planner_binary`)."""


class PlannerStartError(EbmpcError):
    """A local planner did not come up: it exited at start, or did not serve in time.
    ``log_tail`` holds the last lines of its log (also in the message)."""

    def __init__(self, message: str, log_tail: str) -> None:
        self.log_tail = log_tail
        super().__init__(f"{message}\n{log_tail}" if log_tail else message)


class PortInUseError(PlannerStartError):
    """The port a local planner was to listen on is taken."""


class DataDirLockedError(PlannerStartError):
    """Another planner serves the data directory a local planner was to use."""
