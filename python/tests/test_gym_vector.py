"""The Gymnasium driver over a vector env: each copy an agent, episodes cut at the copy's own
end, Gymnasium's autoreset in each of its modes never carried into a stored transition, and
exactly the episodes asked for (against scripted agents; real learning is the e2e tests').
"""

from __future__ import annotations

from typing import Any, List, Optional, Tuple

import gymnasium
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode, SyncVectorEnv

from ebmpc import gym as driver
from ebmpc.progress import Progress


class Walk(gymnasium.Env[np.ndarray, np.ndarray]):
    """``x`` moves by the action; ``terminated`` once it passes 1, ``truncated`` at ``limit``
    steps. Its observation is ``[x, t, resets]``: ``t`` restarts at 0 on every reset, so a
    transition across a reset would show ``t`` going down."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.observation_space = gymnasium.spaces.Box(-100.0, 100.0, (3,), np.float64)
        self.action_space = gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)
        self.resets = 0

    def reset(
        self, *, seed: Optional[int] = None, options: Optional[dict[str, Any]] = None
    ) -> Tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        self.x, self.t = 0.0, 0
        self.resets += 1
        return self._obs(), {}

    def _obs(self) -> np.ndarray:
        return np.array([self.x, float(self.t), float(self.resets)])

    def step(self, action: np.ndarray) -> Tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self.x += float(action[0])
        self.t += 1
        return self._obs(), 1.0, self.x > 1.0, self.t >= self.limit, {}


class ScriptedAgent:
    """An agent whose actions are ``step``; it records what it is sent, per episode."""

    def __init__(self, name: str, step: float) -> None:
        self.name = name
        self.step_size = step
        self.episode = 0
        self.models_version = 1
        self.last_stats = {"source": "planned"}
        self.episodes: List[List[Tuple[List[float], Optional[float]]]] = []
        self.ends: List[Tuple[List[float], float, str]] = []
        self._pending = False
        self._in_episode = False

    def submit(self, obs: List[float], reward: Optional[float] = None) -> None:
        assert not self._pending, "an action was not collected"
        if reward is None:
            assert not self._in_episode, "a new episode began before the last one ended"
            self.episodes.append([])
            self._in_episode = True
        else:
            assert self._in_episode, "a step outside an episode"
        self.episodes[-1].append((obs, reward))
        self._pending = True

    def result(self) -> List[float]:
        assert self._pending
        self._pending = False
        return [self.step_size]

    def end(self, obs: List[float], reward: float, kind: str, wait: bool = True) -> None:
        assert self._in_episode and not self._pending
        self.ends.append((obs, reward, kind))
        self._in_episode = False
        self.episode += 1


def check_no_transition_across_a_reset(agent: ScriptedAgent) -> None:
    for steps, (last, _, _) in zip(agent.episodes, agent.ends):
        observations = [obs for obs, _ in steps] + [last]
        # Within an episode `t` counts 0, 1, 2, ... and the reset counter never moves.
        assert [o[1] for o in observations] == [float(t) for t in range(len(observations))]
        assert len({o[2] for o in observations}) == 1


@pytest.mark.parametrize(
    "mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP, AutoresetMode.DISABLED]
)
def test_each_copy_is_an_agent_and_no_transition_crosses_a_reset(mode: AutoresetMode) -> None:
    # Copies with different steps end at different times: 0.6 -> 2 steps (terminated),
    # 0.3 -> 4 steps, 0.05 -> the 5-step limit (truncated).
    env = SyncVectorEnv([lambda: Walk(limit=5)] * 3, autoreset_mode=mode)
    agents = [ScriptedAgent(f"gym-{i}", s) for i, s in enumerate([0.6, 0.3, 0.05])]
    results: List[driver.EpisodeResult] = []
    with Progress(7, enabled=False) as bar:
        driver._VectorDriver(env, agents, bar, results.append).run(driver.Budget(7, None), seed=0)  # type: ignore[arg-type]
    assert len(results) == 7, "exactly the episodes asked for, none cut short"
    for agent in agents:
        check_no_transition_across_a_reset(agent)
        assert len(agent.episodes) == len(agent.ends), "every started episode ended"
    by_agent = {a.name: [r for r in results if r.agent == a.name] for a in agents}
    assert all(r.steps == 2 and r.end == "terminated" for r in by_agent["gym-0"])
    assert all(r.steps == 4 and r.end == "terminated" for r in by_agent["gym-1"])
    assert all(r.steps == 5 and r.end == "time_limit" for r in by_agent["gym-2"])
    # The fastest copy plays most: over 10 vector steps, 2-step episodes fill more of them.
    assert len(by_agent["gym-0"]) > len(by_agent["gym-2"])
    for r in results:
        assert r.episode_return == pytest.approx(r.steps) and r.planned == r.steps
    for agent in agents:
        assert [r.episode for r in by_agent[agent.name]] == list(range(len(agent.ends)))
        # The last observation of each episode is its own, with every step's reward sent.
        for steps, (last, reward, _) in zip(agent.episodes, agent.ends):
            assert reward == 1.0 and all(r == 1.0 for _, r in steps[1:])
            assert last[1] == float(len(steps))
    env.close()


def test_a_step_budget_starts_episodes_until_its_steps_are_taken() -> None:
    env = SyncVectorEnv([lambda: Walk(limit=5)] * 3)
    agents = [ScriptedAgent(f"gym-{i}", s) for i, s in enumerate([0.6, 0.3, 0.05])]
    results: List[driver.EpisodeResult] = []
    with Progress(None, total_steps=12, enabled=False) as bar:
        driver._VectorDriver(env, agents, bar, results.append).run(  # type: ignore[arg-type]
            driver.Budget(None, 12), seed=0
        )
    env.close()
    for agent in agents:
        check_no_transition_across_a_reset(agent)
        assert len(agent.episodes) == len(agent.ends), "every started episode ended"
    # The three copies step together: 12 steps are taken within the fourth vector step
    # (2 + 2 + 2 at vector step 2, ...); episodes started before that run to their end.
    taken = sum(r.steps for r in results)
    assert taken >= 12 and bar.steps == taken
    by_agent = {a.name: [r.steps for r in results if r.agent == a.name] for a in agents}
    assert by_agent == {"gym-0": [2, 2], "gym-1": [4], "gym-2": [5]}, by_agent


def test_a_budget_needs_episodes_or_steps() -> None:
    with pytest.raises(ValueError):
        driver.Budget(None, None)
    with pytest.raises(ValueError):
        driver.Budget(0, None)
    both = driver.Budget(3, 100)
    assert both.allows(2, 99) and not both.allows(3, 10) and not both.allows(1, 100)
    assert driver.Budget(None, 5).allows(1000, 4)


def test_the_spec_of_a_vector_env_is_that_of_one_copy() -> None:
    env = gymnasium.make_vec("Pendulum-v1", num_envs=2, vectorization_mode="sync")
    try:
        spec = driver._spec_of(env, {})
    finally:
        env.close()
    single = gymnasium.make("Pendulum-v1")
    try:
        assert spec == driver._spec_of(single, {})
    finally:
        single.close()
    assert (spec["obs_dim"], spec["act_dim"], spec["episode_len"]) == (3, 1, 200)
