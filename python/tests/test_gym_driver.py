"""The Gymnasium driver (``python -m ebmpc.gym``): its episode loop against a scripted agent, its
command line, and its exit status on a planner's refusal (against the real daemon).

Learning real environments is the end-to-end tests' (``tests/tests/e2e/gym_driver.rs``).
"""

from __future__ import annotations

from typing import Any, List, Optional, Tuple

import numpy as np
import pytest

from conftest import Daemon
from ebmpc import gym as driver


class Box:
    def __init__(self, low: List[float], high: List[float]) -> None:
        self.low, self.high = np.array(low, np.float32), np.array(high, np.float32)
        self.shape, self.dtype = self.low.shape, np.float32


class Walk:
    """A 2-D walk that ends (``terminated``) once ``x`` passes 1, or is cut at ``limit`` steps
    (``truncated``): what Gymnasium's ``TimeLimit`` wrapper reports."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.observation_space = Box([-5.0, -5.0], [5.0, 5.0])
        self.action_space = Box([-1.0], [1.0])
        self.actions: List[Any] = []

    def reset(self, seed: Optional[int] = None) -> Tuple[Any, dict[str, Any]]:
        self.x, self.t = 0.0, 0
        return np.array([self.x, 0.0]), {}

    def step(self, action: Any) -> Tuple[Any, float, bool, bool, dict[str, Any]]:
        self.actions.append(action)
        self.x += float(action[0])
        self.t += 1
        return np.array([self.x, float(self.t)]), 0.5, self.x > 1.0, self.t >= self.limit, {}


class ScriptedAgent:
    """Answers every observation with ``step``; records what it was sent."""

    def __init__(self, step: float) -> None:
        self.step = step
        self.sent: List[Tuple[List[float], Optional[float]]] = []
        self.ended: List[Tuple[List[float], float, str]] = []
        self.last_stats = {"source": "planned"}
        self.models_version = 3
        self.name = "gym-0"

    def act(self, obs: List[float], reward: Optional[float] = None) -> List[float]:
        self.sent.append((obs, reward))
        return [self.step]

    def end(self, obs: List[float], reward: float, kind: str) -> None:
        self.ended.append((obs, reward, kind))


def test_a_terminated_episode_ends_as_terminated_with_every_reward_sent() -> None:
    env, agent = Walk(limit=100), ScriptedAgent(0.4)
    result = driver.run_episode(env, agent, 7, seed=0)  # type: ignore[arg-type]
    # x: 0.4, 0.8, 1.2 -> the third step passes 1.
    assert (result.episode, result.steps, result.end) == (7, 3, "terminated")
    assert result.episode_return == pytest.approx(1.5) and result.planned == 3
    assert [reward for _, reward in agent.sent] == [None, 0.5, 0.5]
    assert agent.ended == [([pytest.approx(1.2), 3.0], 0.5, "terminated")]
    assert all(a.dtype == np.float32 and a.shape == (1,) for a in env.actions)


def test_a_truncated_episode_ends_as_a_time_limit() -> None:
    env, agent = Walk(limit=4), ScriptedAgent(0.1)
    result = driver.run_episode(env, agent, 0, seed=None)  # type: ignore[arg-type]
    assert (result.steps, result.end, result.models_version) == (4, "time_limit", 3)
    assert agent.ended[0][2] == "time_limit" and len(agent.sent) == 4


def test_a_non_finite_observation_stops_the_driver_before_it_is_sent() -> None:
    env, agent = Walk(limit=10), ScriptedAgent(float("nan"))
    with pytest.raises(driver.UndrivableEnvironment, match="non-finite observation"):
        driver.run_episode(env, agent, 0, seed=None)  # type: ignore[arg-type]
    assert len(agent.sent) == 1 and not agent.ended


def test_overrides_are_json_or_strings() -> None:
    assert driver.parse_override("population=100") == ("population", 100)
    assert driver.parse_override("sample_dynamics=true") == ("sample_dynamics", True)
    assert driver.parse_override("optimizer=icem") == ("optimizer", "icem")
    assert driver.parse_override('epoch_schedule={"constant": null}') == (
        "epoch_schedule", {"constant": None})
    with pytest.raises(Exception, match="key=value"):
        driver.parse_override("population")


def test_every_planner_code_has_its_own_exit_status() -> None:
    statuses = list(driver.EXIT_STATUS.values())
    assert len(set(statuses)) == len(statuses) == 13
    reserved = {0, 1, 2, driver.EXIT_ENVIRONMENT, driver.EXIT_CLIENT, driver.EXIT_UNKNOWN_CODE}
    assert not reserved & set(statuses)


def test_an_unknown_environment_exits_with_its_status(capsys: pytest.CaptureFixture[str]) -> None:
    status = driver.main(["--env", "NoSuchEnv-v0", "--run", "r", "--connect", "tcp/127.0.0.1:9"])
    assert status == driver.EXIT_ENVIRONMENT
    assert "NoSuchEnv-v0" in capsys.readouterr().err


def test_a_refused_formula_exits_with_the_planners_code(
    daemon: Daemon, capsys: pytest.CaptureFixture[str]
) -> None:
    status = driver.main([
        "--env", "Pendulum-v1", "--run", "bad-formula", "--episodes", "1",
        "--connect", daemon.endpoint, "--reward-expression=-s_next[7]",
    ])
    err = capsys.readouterr().err
    assert status == driver.EXIT_STATUS["refused"], err
    assert "refused" in err and "s_next[7]" in err


TINY = {
    "dynamics_hidden_layers": 2, "dynamics_hidden_size": 16, "dynamics_epochs": 3,
    "energy_hidden_layers": 2, "energy_hidden_size": 16, "energy_epochs": 3,
    "population": 20, "elites": 4, "horizon": 5, "cem_iterations": 2,
    "exploration_episodes": 1,
}


def test_learn_drives_a_vector_env_as_agents_of_one_run_and_resumes_it(daemon: Daemon) -> None:
    import ebmpc

    with ebmpc.Planner(connect=daemon.endpoint) as planner:
        first = driver.learn(
            "Pendulum-v1", 3, overrides=TINY, planner=planner, num_envs=2, progress=False,
        )
        # Pendulum's episodes all last 200 steps: the two copies end together, then one more.
        assert sorted((r.agent, r.episode) for r in first) == [
            ("gym-0", 0), ("gym-0", 1), ("gym-1", 0)]
        assert all(r.steps == 200 and r.end == "time_limit" for r in first)
        (report,) = planner.status()
        (run,) = [r for r in report["runs"] if r["name"] == "Pendulum-v1"]
        assert (run["episodes"], run["transitions"]) == (3, 600), report
        # The run is named after the environment: learning it again continues it.
        again = driver.learn("Pendulum-v1", 1, overrides=TINY, planner=planner, progress=False)
        assert [(r.agent, r.episode, r.planned) for r in again] == [("gym-0", 2, 200)]


def test_the_progress_line_counts_episodes_steps_and_returns() -> None:
    import io

    from ebmpc.progress import Progress

    out, lines = io.StringIO(), io.StringIO()
    with Progress(4, stream=out, enabled=True) as bar:
        bar.step(30)
        bar.episode(-12.5)
        with bar.paused():
            print("episode 0: ...", file=lines)
        bar.step(10)
        bar.episode(-3.0)
        assert bar.line().startswith("[##########----------] 2/4 episodes | 40 steps | "
                                     "return -3.0 (best -3.0)")
    assert "2/4 episodes" in out.getvalue() and lines.getvalue() == "episode 0: ...\n"
    # A step budget fills the bar by the steps when it is nearer its end than the episodes.
    with Progress(None, total_steps=200, stream=io.StringIO(), enabled=True) as bar:
        bar.step(150)
        bar.episode(1.0)
        assert bar.line().startswith("[###############-----] 1 episodes | 150/200 steps")
    quiet = io.StringIO()
    with Progress(1, stream=quiet) as bar:  # not a terminal: draws nothing
        bar.episode(1.0)
    assert quiet.getvalue() == ""


def test_the_command_drives_num_envs_copies_and_names_each_episodes_agent(
    daemon: Daemon, capsys: pytest.CaptureFixture[str]
) -> None:
    overrides = [arg for key, value in TINY.items() for arg in ("--override", f"{key}={value}")]
    status = driver.main([
        "--env", "Pendulum-v1", "--episodes", "2", "--num-envs", "2", "--run", "cli-vector",
        "--connect", daemon.endpoint, *overrides,
    ])
    out = capsys.readouterr()
    assert status == 0, out.err
    lines = sorted(line.split(":")[0] for line in out.out.splitlines())
    assert lines == ["gym-0 episode 0", "gym-1 episode 0"], out.out
    assert out.err == "", "no progress line where stderr is not a terminal"


def test_a_learned_termination_and_a_step_budget_for_an_environment_that_ends_early(
    daemon: Daemon,
) -> None:
    import ebmpc

    seen: List[dict[str, Any]] = []
    overrides = {**TINY, "exploration_steps": 1000}
    with ebmpc.Planner(connect=daemon.endpoint) as planner:
        results = driver.learn(
            "InvertedPendulum-v5", steps=60, overrides=overrides, planner=planner,
            progress=False, on_spec=seen.append,
        )
        (report,) = planner.status()
    # No termination given: the planner learns it.
    assert seen[0]["termination"] == "learned"
    # Random episodes fall within a few steps: many of them, until 60 steps are taken (the
    # last one started below 60 and ran to its end).
    steps = [r.steps for r in results]
    assert len(results) > 2 and all(r.end == "terminated" for r in results), steps
    assert sum(steps) >= 60 > sum(steps[:-1]), steps
    assert all(r.planned == 0 for r in results), "exploring: 1000 random steps first"
    (run,) = [r for r in report["runs"] if r["name"] == "InvertedPendulum-v5"]
    assert (run["episodes"], run["transitions"]) == (len(results), sum(steps)), run
    # Models trained now would not be used: retraining waits for the exploration steps.
    assert run["models_version"] == 0 and run.get("last_retraining") is None, run


def test_status_and_events_report_the_learned_terminations_held_out_accuracy(
    daemon: Daemon,
) -> None:
    import ebmpc

    with ebmpc.Planner(connect=daemon.endpoint) as planner:
        with planner.events("pendulum-ends") as events:
            results = driver.learn(
                # Every CEM iteration run: the episodes do not depend on the machine's load.
                "InvertedPendulum-v5", steps=80, overrides={**TINY, "deadline_ms": 0},
                planner=planner, run="pendulum-ends", progress=False,
            )
            (report,) = planner.status()
            updates = []
            while True:
                try:
                    event = events.next(timeout=0.5)
                except ebmpc.EventTimeout:
                    break
                if isinstance(event, ebmpc.ModelsUpdated):
                    updates.append(event)
    assert sum(r.steps for r in results) >= 80
    (run,) = [r for r in report["runs"] if r["name"] == "pendulum-ends"]
    held = run["last_retraining"]["termination_accuracy"]
    assert held["held_out"] > 0 and held["terminations"] >= 0, held
    assert 0.0 <= held["accuracy"] <= 1.0 and 0.0 <= held["recall"] <= 1.0, held
    # The retrainings report it in their events too (once an end was in the training data).
    assert any(u.termination_accuracy is not None for u in updates), updates
