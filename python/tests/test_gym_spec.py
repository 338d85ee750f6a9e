"""Task specs from Gymnasium-like spaces (no Gymnasium, no planner needed)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional, Tuple

import pytest

from ebmpc.gym_spec import task_name, task_spec_from_env, task_spec_from_spaces


@dataclass
class Box:
    low: List[float]
    high: List[float]
    shape: Tuple[int, ...] = ()

    def __post_init__(self) -> None:
        self.shape = self.shape or (len(self.low),)


@dataclass
class Discrete:
    n: int
    shape: Tuple[int, ...] = ()


@dataclass
class EnvSpec:
    id: str
    max_episode_steps: Optional[int]


@dataclass
class Pendulum:
    """Gymnasium's Pendulum-v1 as its spaces describe it."""

    spec: Optional[EnvSpec] = field(default_factory=lambda: EnvSpec("Pendulum-v1", 200))
    observation_space: Any = field(default_factory=lambda: Box([-1.0, -1.0, -8.0], [1.0, 1.0, 8.0]))
    action_space: Any = field(default_factory=lambda: Box([-2.0], [2.0]))
    metadata: Dict[str, Any] = field(default_factory=lambda: {"render_fps": 30})


def test_pendulum_spec() -> None:
    spec = task_spec_from_env(Pendulum())
    assert spec == {
        "name": "Pendulum-v1",
        "obs_dim": 3,
        "act_dim": 1,
        "action_low": [-2.0],
        "action_high": [2.0],
        "episode_len": 200,
        "control_dt": pytest.approx(1 / 30),
        "model": {"declared": {"angles": [], "absolute": []}},
        "termination": "learned",
        "reward": "learned",
        "observation_bounds": {"low": [-1.0, -1.0, -8.0], "high": [1.0, 1.0, 8.0]},
    }
    given = task_spec_from_env(Pendulum(), reward="-(s_next[2] ** 2)")
    assert given["reward"] == {"expression": "-(s_next[2] ** 2)"}
    based = task_spec_from_env(Pendulum(), angles=[2], base_preset="reacher3d")
    assert based["base_preset"] == "reacher3d"
    assert based["model"] == {"declared": {"angles": [2], "absolute": []}}


def test_unbounded_observations_have_no_bounds_and_mujoco_dt_wins() -> None:
    env = Pendulum(observation_space=Box([-math.inf] * 4, [math.inf] * 4))
    env.unwrapped = type("Unwrapped", (), {"dt": 0.04})()  # type: ignore[attr-defined]
    spec = task_spec_from_env(env)
    assert "observation_bounds" not in spec and spec["control_dt"] == 0.04 and spec["obs_dim"] == 4


def test_what_a_planner_cannot_learn_is_refused() -> None:
    with pytest.raises(ValueError, match="not a Box"):
        task_spec_from_env(Pendulum(action_space=Discrete(3)))
    with pytest.raises(ValueError, match="unbounded"):
        task_spec_from_env(Pendulum(action_space=Box([-math.inf], [1.0])))
    with pytest.raises(ValueError, match="episode length"):
        task_spec_from_env(Pendulum(spec=EnvSpec("Pendulum-v1", None)))
    with pytest.raises(ValueError, match="vector"):
        task_spec_from_spaces("x", Box([0.0] * 4, [1.0] * 4, (2, 2)), Box([-1.0], [1.0]), 10, 0.1)
    with pytest.raises(ValueError, match="angle"):
        task_spec_from_spaces("x", Box([0.0], [1.0]), Box([-1.0], [1.0]), 10, 0.1, angles=[1])
    with pytest.raises(ValueError, match="control period"):
        task_spec_from_env(Pendulum(metadata={}))


def test_task_names_are_key_chunks() -> None:
    assert task_name("ALE/Pong-v5") == "ALE_Pong-v5"
    assert task_name("x" * 100) == "x" * 64
    with pytest.raises(ValueError):
        task_name("")
