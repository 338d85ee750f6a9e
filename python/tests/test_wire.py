"""The package's messages against the JSON schemas of the Rust types; no planner needed."""

from __future__ import annotations

import math

import jsonschema
import pytest

import ebmpc
from ebmpc import errors, events, wire
from schema_check import validate


def test_protocol_version_is_the_schemas() -> None:
    index = wire.schema("protocol")
    assert ebmpc.PROTOCOL_VERSION == index["protocol_version"] >= 3
    for name in index["messages"]:
        assert wire.schema(name)["$schema"].startswith("https://json-schema.org/")


def test_built_messages_are_valid() -> None:
    validate("AttachRequest", wire.attach_request("a-0", "cartpole", None, None, "sync", 0, None))
    validate(
        "AttachRequest",
        wire.attach_request("a-0", "ant", "pets", {"population": 40, "deadline_ms": 0},
                            "async", 7, 2**64 - 1),
    )
    validate("Observation", wire.observation(0, 0, [0.0, 1.0, 2.0, 3.0], 5))
    validate("Observation", wire.observation(2, 9, [1, 2], 2**63, reward=-0.5, end="terminated",
                                             applied=[0.25]))


def test_the_schemas_refuse_what_the_planner_refuses() -> None:
    request = wire.attach_request("a-0", "cartpole", None, {"populaton": 40}, "sync", 0, None)
    with pytest.raises(jsonschema.ValidationError):
        validate("AttachRequest", request)  # a mistyped override
    unnamed = wire.attach_request("a-0", "cartpole", None, None, "sync", 0, None)
    unnamed["spec"]["task"] = 7  # a task is named by a string since protocol 4
    with pytest.raises(jsonschema.ValidationError):
        validate("AttachRequest", unnamed)
    observation = wire.observation(0, 1, [0.0], 5, end="time_limit")
    observation["end"] = "crashed"
    with pytest.raises(jsonschema.ValidationError):
        validate("Observation", observation)
    with pytest.raises(jsonschema.ValidationError):
        validate("Observation", wire.observation(-1, 0, [0.0], 5))
    # A field a message does not have is refused in every message, as the planner refuses it.
    coloured = wire.attach_request("a-0", "cartpole", None, None, "sync", 0, None)
    coloured["spec"]["colour"] = "red"
    with pytest.raises(jsonschema.ValidationError):
        validate("AttachRequest", coloured)
    extra = wire.observation(0, 0, [0.0], 5)
    extra["colour"] = "red"
    with pytest.raises(jsonschema.ValidationError):
        validate("Observation", extra)


def test_every_error_code_has_its_exception() -> None:
    codes = [variant["const"] for variant in wire.schema("ErrorReport")["$defs"]["ErrorCode"]["oneOf"]]
    assert sorted(codes) == sorted(errors.ERROR_CLASSES)
    for code in codes:
        report = {"version": wire.PROTOCOL_VERSION, "code": code, "message": "why",
                  "episode": 1, "step": 2}
        validate("ErrorReport", report)
        error = errors.from_report(report)
        assert type(error).CODE == code == error.code
        assert (error.message, error.episode, error.step) == ("why", 1, 2)
        assert isinstance(error, ebmpc.PlannerError)
    newer = errors.from_report({"code": "from_the_future", "message": "m"})
    assert type(newer) is ebmpc.PlannerError and newer.code == "from_the_future"


def test_events_parse_into_typed_values() -> None:
    message = {"version": wire.PROTOCOL_VERSION, "run": "r",
               "kind": {"EpisodeFinished": {"agent": "a", "episode": 3, "episode_return": 1.5,
                                            "steps": 10, "end": "terminated"}}}
    validate("RunEvent", message)
    assert events.parse_event(message) == ebmpc.EpisodeFinished("r", "a", 3, 1.5, 10, "terminated")
    message["kind"] = {"ModelsUpdated": {"models_version": 2, "dynamics_loss": -1.0,
                                         "energy_loss": 0.5, "seconds": 0.25}}
    validate("RunEvent", message)
    assert events.parse_event(message) == ebmpc.ModelsUpdated("r", 2, -1.0, 0.5, 0.25)
    message["kind"]["ModelsUpdated"]["reward_loss"] = 0.125  # a learned reward's model
    validate("RunEvent", message)
    assert events.parse_event(message) == ebmpc.ModelsUpdated("r", 2, -1.0, 0.5, 0.25, 0.125)
    message["kind"]["ModelsUpdated"]["termination_accuracy"] = {  # a learned termination's
        "held_out": 40, "terminations": 4, "accuracy": 0.975, "recall": 0.75}
    validate("RunEvent", message)
    assert events.parse_event(message) == ebmpc.ModelsUpdated(
        "r", 2, -1.0, 0.5, 0.25, 0.125, ebmpc.TerminationAccuracy(40, 4, 0.975, 0.75))
    for bad in ({"run": "r", "kind": {"Exploded": {}}},
                {"run": "r", "kind": {"TrainingStarted": {}}},
                {"run": "r", "kind": {"EpisodeFinished": {"agent": "a", "episode": 0,
                                                          "episode_return": 0, "steps": 1,
                                                          "end": "crashed"}}}):
        with pytest.raises(ebmpc.ProtocolError):
            events.parse_event(bad)


def test_a_task_spec_travels_whole_where_the_protocol_takes_one() -> None:
    spec = {"name": "my-arm", "obs_dim": 3, "act_dim": 1}
    run_spec = wire.schema("AttachRequest")["$defs"]["RunSpec"]["properties"]
    assert wire.TAKES_TASK_SPECS == ("task_spec" in run_spec)
    if wire.TAKES_TASK_SPECS:
        request = wire.attach_request("a", spec, None, None, "sync", 0, None)
        assert request["spec"]["task"] == "my-arm" and request["spec"]["task_spec"] == spec
        with pytest.raises(ValueError, match="name"):
            wire.attach_request("a", {"obs_dim": 3}, None, None, "sync", 0, None)
    else:
        # Such a planner would ignore the spec and plan for whatever catalog task it names.
        with pytest.raises(ValueError, match="task names only"):
            wire.attach_request("a", spec, None, None, "sync", 0, None)
    assert wire.attach_request("a", "ant", None, None, "sync", 0, None)["spec"]["task"] == "ant"


def test_non_finite_numbers_are_refused_before_sending() -> None:
    with pytest.raises(ValueError, match="non-finite"):
        wire.encode(wire.observation(0, 0, [math.nan], 1))
    with pytest.raises(ebmpc.ProtocolError, match="protocol version"):
        wire.decode(b'{"version": 2}', "action")
    with pytest.raises(ebmpc.ProtocolError, match="undecodable"):
        wire.decode(b"\x00\x01", "action")
