"""The package against a real planner daemon: attach, episodes, events, status, typed errors.

Tiny networks and a small search (attach overrides): these tests check the client, not the
learning. Every JSON message on the run's keys, both directions, is checked against the schema.
"""

from __future__ import annotations

import json
import math
import threading
import time
from typing import Any, Dict, List, Tuple

import pytest
import zenoh

import ebmpc
from conftest import Daemon, free_endpoint
from schema_check import validate

TINY = {
    "dynamics_hidden_layers": 2, "dynamics_hidden_size": 16, "dynamics_epochs": 3,
    "energy_hidden_layers": 2, "energy_hidden_size": 16, "energy_epochs": 3,
    "population": 20, "elites": 4, "horizon": 5, "cem_iterations": 2,
    "exploration_episodes": 1,
}
STEPS = 12


class Pendulum:
    """A damped pendulum on a cart-pole's observation layout ``[x, theta, x_dot, theta_dot]``;
    the planner learns whatever it is fed, so its dynamics need not be the simulator's."""

    def __init__(self) -> None:
        self.state = [0.0, 0.1, 0.0, 0.0]

    def step(self, force: float) -> Tuple[List[float], float]:
        x, theta, x_dot, theta_dot = self.state
        force = max(-3.0, min(3.0, force))
        x_dot += 0.04 * force
        theta_dot += 0.04 * (-9.81 * math.sin(theta) - 0.1 * theta_dot + force)
        self.state = [x + 0.04 * x_dot, theta + 0.04 * theta_dot, x_dot, theta_dot]
        return list(self.state), -(theta - math.pi) ** 2 - 0.01 * force**2


class Wiretap:
    """Every JSON sample under a run's keys, to check against the schemas."""

    def __init__(self, endpoint: str, run: str) -> None:
        config = zenoh.Config()
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("connect/endpoints", json.dumps([endpoint]))
        self.session = zenoh.open(config)
        self.seen: List[Tuple[str, Dict[str, Any]]] = []
        self.lock = threading.Lock()
        self.subscriber = self.session.declare_subscriber(f"ebmpc/runs/{run}/**", self.receive)

    def receive(self, sample: zenoh.Sample) -> None:
        if str(sample.encoding).startswith("application/json"):
            with self.lock:
                self.seen.append((str(sample.key_expr), json.loads(sample.payload.to_bytes())))

    def check(self) -> Dict[str, int]:
        """Validates every message seen; the count per message kind."""
        kinds = {"obs": "Observation", "act": "Action", "error": "ErrorReport", "json": "RunEvent"}
        counts: Dict[str, int] = {}
        with self.lock:
            for key, message in self.seen:
                kind = kinds[key.rsplit("/", 1)[1]]
                validate(kind, message)
                counts[kind] = counts.get(kind, 0) + 1
        return counts

    def close(self) -> None:
        self.session.close()


def play(agent: ebmpc.Agent, steps: int) -> Tuple[float, List[Dict[str, Any]]]:
    """One episode of ``steps`` transitions; the sum of the rewards sent, and every action's stats."""
    env = Pendulum()
    total, stats = 0.0, []
    action = agent.act(env.state)
    for t in range(steps):
        stats.append(dict(agent.last_stats))
        assert len(action) == 1 and abs(action[0]) <= 3.0 + 1e-4, action
        obs, reward = env.step(action[0])
        total += reward
        if t == steps - 1:
            finished = agent.end(obs, reward, "time_limit", applied=[max(-3.0, min(3.0, action[0]))])
            assert finished is not None
            assert (finished.run, finished.agent, finished.steps, finished.end) == (
                agent.run, agent.name, steps, "time_limit")
            assert finished.episode_return == pytest.approx(total, abs=1e-3)
        else:
            action = agent.act(obs, reward, applied=[max(-3.0, min(3.0, action[0]))])
    return total, stats


def test_episodes_events_and_status(daemon: Daemon) -> None:
    tap = Wiretap(daemon.endpoint, "py-pkg")
    try:
        with ebmpc.Planner(connect=daemon.endpoint, attach_timeout=30) as planner:
            with planner.events("py-pkg", timeout=120) as events:
                agent = planner.attach("py-pkg", "cartpole", overrides=TINY, agent="py-0", seed=3)
                assert (agent.planner_id, agent.task, agent.mode) == ("py-pkg", "cartpole", "sync")
                assert agent.session != 0 and agent.episode == 0 and not agent.in_episode

                # Episode 0 explores with random actions; episode 1 plans with the models
                # retrained on it (sync mode: its first action waits for them).
                first, stats0 = play(agent, STEPS)
                second, stats1 = play(agent, STEPS)
                assert {s["source"] for s in stats0} == {"random"}
                assert {s["source"] for s in stats1} == {"planned"}
                assert min(s["models_version"] for s in stats1) >= 1
                assert agent.episode == 2

                seen: List[ebmpc.RunEvent] = []
                while not any(isinstance(e, ebmpc.EpisodeFinished) and e.episode == 1 for e in seen):
                    seen.append(next(events))
            finished = [e for e in seen if isinstance(e, ebmpc.EpisodeFinished)]
            assert [(e.agent, e.episode, e.steps) for e in finished] == [("py-0", 0, STEPS), ("py-0", 1, STEPS)]
            assert finished[0].episode_return == pytest.approx(first, abs=1e-3)
            assert finished[1].episode_return == pytest.approx(second, abs=1e-3)
            assert any(isinstance(e, ebmpc.TrainingStarted) and e.transitions == STEPS for e in seen)
            updates = [e for e in seen if isinstance(e, ebmpc.ModelsUpdated)]
            assert updates and updates[0].models_version >= 1 and math.isfinite(updates[0].dynamics_loss)

            reports = planner.status()
            assert [r["planner_id"] for r in reports] == ["py-pkg"]
            validate("PlannerStatus", reports[0])
            (run,) = [r for r in reports[0]["runs"] if r["name"] == "py-pkg"]
            assert (run["task"], run["episodes"], run["transitions"]) == ("cartpole", 2, 2 * STEPS)
            assert run["agents"] == ["py-0"]
            assert [r["planner_id"] for r in planner.status("py-pkg")] == ["py-pkg"]
            with pytest.raises(ebmpc.NoPlannerError):
                planner.status("absent", timeout=1)
            agent.close()
        counts = tap.check()
        assert counts["Observation"] == 2 * (STEPS + 1), counts
        assert counts["Action"] == 2 * STEPS, counts
        assert counts["RunEvent"] >= 4, counts
    finally:
        tap.close()


def test_hostile_requests_raise_typed_errors(daemon: Daemon) -> None:
    with ebmpc.Planner(connect=daemon.endpoint, attach_timeout=30) as planner:
        with pytest.raises(ebmpc.RefusedError) as refused:
            planner.attach("py-bad", "cartpole", overrides={"population": 0})
        assert refused.value.code == "refused" and "population" in refused.value.message
        with pytest.raises(ebmpc.RefusedError) as limit:
            planner.attach("py-big", "cartpole", overrides={"dynamics_hidden_size": 4_000_000_000})
        assert "limit" in limit.value.message
        with pytest.raises(ebmpc.MalformedError) as mistyped:
            planner.attach("py-typo", "cartpole", overrides={"populaton": 40})
        assert "populaton" in mistyped.value.message
        # Protocol 3 decodes the task as an enum of the catalog (malformed); a planner that
        # takes task specs looks the name up (unknown_task). Either way the name is in it.
        with pytest.raises((ebmpc.MalformedError, ebmpc.UnknownTaskError), match="no-such-task"):
            planner.attach("py-task", "no-such-task")

        agent = planner.attach("py-ok", "cartpole", overrides=TINY, agent="py-0")
        # Someone else under the same name, without the session token: refused, naming it.
        with pytest.raises(ebmpc.RefusedError, match="py-0"):
            planner.attach("py-ok", "cartpole", overrides=TINY, agent="py-0")
        # An observation of the wrong dimension is the planner's `dimension` error.
        with pytest.raises(ebmpc.DimensionError) as wrong:
            agent.act([0.0, 0.0, 0.0])
        assert wrong.value.episode == 0 and wrong.value.step == 0
        # Nothing of it was used: the same step, well formed, is answered.
        assert len(agent.act([0.0, 0.1, 0.0, 0.0])) == 1
        with pytest.raises(ValueError, match="non-finite"):
            agent.act([math.inf, 0.0, 0.0, 0.0], reward=0.0)
        # ... and left the agent where it was: the next step is step 1.
        assert len(agent.act([0.0, 0.1, 0.0, 0.0], reward=0.0)) == 1
        assert agent.step == 1
        # Bytes that decode to nothing on the agent's action and error keys (a stray or hostile
        # publisher) are skipped: the next step is answered as if they had not come.
        tap = Wiretap(daemon.endpoint, "py-ok")
        try:
            for channel in ("act", "error"):
                tap.session.put(f"ebmpc/runs/py-ok/agents/py-0/{channel}", b"\xff not json")
            time.sleep(0.5)
            assert len(agent.act([0.0, 0.1, 0.0, 0.0], reward=0.0)) == 1
            assert agent.step == 2
        finally:
            tap.close()
        agent.close()


def test_no_planner_is_an_error_not_a_hang() -> None:
    with ebmpc.Planner(connect=free_endpoint()) as planner:
        with pytest.raises(ebmpc.NoPlannerError, match="no planner answered"):
            planner.attach("py-run", "cartpole", timeout=1)
        with pytest.raises(ebmpc.NoPlannerError):
            planner.status(timeout=0.5)


def test_an_attach_query_that_times_out_is_asked_again() -> None:
    """A planner taking a run over may need longer than one attach query waits (it loads the
    run's replay and models): zenoh then ends the query with its own error reply, which is no
    refusal. The agent asks again until its patience runs out, presenting the same token as
    the first time: had the lost answer accepted it, the planner knows it by that token."""
    endpoint = free_endpoint()
    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    slow_planner = zenoh.open(config)
    queries: List[float] = []
    claims: List[Any] = []
    held: List[zenoh.Query] = []

    def answer(query: zenoh.Query) -> None:
        queries.append(time.monotonic())
        claims.append(json.loads(query.payload.to_bytes()).get("session"))
        if len(queries) == 1:
            held.append(query)  # still loading: never answered, so the query times out
            return
        accepted = {
            "planner_id": "slow", "task": "cartpole", "mode": "sync", "episodes_done": 0,
            "models_version": 0, "next_episode": 0, "epoch": 1, "session": 7,
        }
        reply = {"version": ebmpc.PROTOCOL_VERSION, "outcome": {"Accepted": accepted}}
        query.reply(query.key_expr, json.dumps(reply), encoding=zenoh.Encoding.APPLICATION_JSON)

    queryable = slow_planner.declare_queryable("ebmpc/runs/py-slow/attach", answer)
    listener = slow_planner.declare_subscriber("ebmpc/runs/py-slow/agents/*/obs", lambda _: None)
    try:
        with ebmpc.Planner(connect=endpoint) as planner:
            agent = planner.attach("py-slow", "cartpole", timeout=12)
            assert (agent.planner_id, agent.session, agent.epoch) == ("slow", 7, 1)
            assert len(queries) == 2 and queries[1] - queries[0] >= 4.5, queries
            assert isinstance(claims[0], int) and 0 < claims[0] < 2**64, claims
            assert claims[1] == claims[0], claims
            agent.close()
    finally:
        listener.undeclare()
        queryable.undeclare()
        held.clear()
        slow_planner.close()
