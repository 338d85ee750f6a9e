"""A task spec derived from a Gymnasium environment's spaces (for the Gymnasium driver).

A planner learns any system with a vector observation and a box action space; Gymnasium
describes one with ``Box`` spaces and ``spec.max_episode_steps``. This module turns those into
the attach message's task spec (``proto/src/task/spec.rs`` of protocol 4): dimensions, action
bounds, the observation bounds when they are finite, the episode length, the control period,
and the reward and termination: each ``learned`` (models trained on the rewards the agent
sends and on the episodes it ends as ``terminated``) unless a formula is given. It reads the spaces by duck typing (``shape``, ``low``, ``high``), so it needs neither
Gymnasium nor NumPy itself. The Gymnasium driver (:mod:`ebmpc.gym`) attaches with it.
"""

from __future__ import annotations

import math
import re
from typing import Any, Dict, List, Optional, Sequence

#: What a task name may hold (proto/src/keys.rs: 1-64 of letters, digits, '-', '_', '.').
_NAME_CHARS = re.compile(r"[^A-Za-z0-9_.-]")


def _flat_floats(values: Any, what: str) -> List[float]:
    try:
        flat = values.reshape(-1).tolist() if hasattr(values, "reshape") else list(values)
        return [float(v) for v in flat]
    except (TypeError, ValueError) as e:
        raise ValueError(f"{what} is not a sequence of numbers: {e}") from None


def _box_bounds(space: Any, what: str) -> tuple[List[float], List[float]]:
    """``(low, high)`` of a one-dimensional box space, or :class:`ValueError` naming the space."""
    shape = getattr(space, "shape", None)
    if not hasattr(space, "low") or not hasattr(space, "high") or shape is None:
        raise ValueError(f"the {what} space {space!r} is not a Box: only Box spaces are supported")
    if len(shape) != 1 or shape[0] < 1:
        raise ValueError(f"the {what} space has shape {tuple(shape)}: a vector (n,) is needed")
    low, high = _flat_floats(space.low, f"{what} low"), _flat_floats(space.high, f"{what} high")
    if len(low) != shape[0] or len(high) != shape[0]:
        raise ValueError(f"the {what} space's bounds do not have its shape {tuple(shape)}")
    return low, high


def task_name(env_id: str) -> str:
    """A valid task name from a Gymnasium id (``ALE/Pong-v5`` -> ``ALE_Pong-v5``)."""
    name = _NAME_CHARS.sub("_", env_id)[:64]
    if not name or name in (".", ".."):
        raise ValueError(f"no task name can be made of `{env_id}`")
    return name


def task_spec_from_spaces(
    name: str,
    observation_space: Any,
    action_space: Any,
    max_episode_steps: Optional[int],
    control_dt: float,
    reward: Optional[str] = None,
    termination: Optional[str] = None,
    angles: Sequence[int] = (),
    base_preset: Optional[str] = None,
) -> Dict[str, Any]:
    """The task spec of a system with these spaces.

    ``reward``/``termination``: formulas over ``s``, ``a``, ``s_next`` (``None``: each is
    learned, the reward from the rewards the agent sends, the termination from the episodes
    it ends as ``terminated``; an environment that never ends its own episodes teaches a
    termination that never fires). ``termination="0"`` is a rule that never ends one.
    ``angles``: observation dimensions that are angles (the model sees their sine and cosine).
    ``base_preset``: the catalog task whose paper sizes a run starts from (``None``: the
    planner's default, ``cartpole``, the smallest).
    Raises :class:`ValueError` for a space that is not a vector ``Box``, unbounded actions, or
    no episode length.
    """
    obs_low, obs_high = _box_bounds(observation_space, "observation")
    act_low, act_high = _box_bounds(action_space, "action")
    if not all(math.isfinite(v) for v in act_low + act_high):
        raise ValueError("the action space is unbounded: the planner samples within finite bounds")
    if max_episode_steps is None or max_episode_steps < 1:
        raise ValueError("the environment has no episode length (spec.max_episode_steps)")
    if not (math.isfinite(control_dt) and control_dt > 0):
        raise ValueError(f"control period {control_dt} s is not a positive number")
    if any(not 0 <= i < len(obs_low) for i in angles):
        raise ValueError(f"angle dimensions {list(angles)} beyond the observation's {len(obs_low)}")
    spec: Dict[str, Any] = {
        "name": name,
        "obs_dim": len(obs_low),
        "act_dim": len(act_low),
        "action_low": act_low,
        "action_high": act_high,
        "episode_len": int(max_episode_steps),
        "control_dt": float(control_dt),
        "model": {"declared": {"angles": list(angles), "absolute": []}},
        "termination": "learned" if termination is None else {"expression": termination},
        "reward": "learned" if reward is None else {"expression": reward},
    }
    if all(math.isfinite(v) for v in obs_low + obs_high):
        spec["observation_bounds"] = {"low": obs_low, "high": obs_high}
    if base_preset is not None:
        spec["base_preset"] = base_preset
    return spec


def task_spec_from_env(
    env: Any,
    reward: Optional[str] = None,
    termination: Optional[str] = None,
    angles: Sequence[int] = (),
    base_preset: Optional[str] = None,
) -> Dict[str, Any]:
    """The task spec of a Gymnasium environment: its id as the name, its spaces, its
    ``spec.max_episode_steps``, and its control period (``dt`` of the unwrapped environment,
    MuJoCo's, or else ``1 / metadata["render_fps"]``); the other arguments are
    :func:`task_spec_from_spaces`'."""
    env_spec = getattr(env, "spec", None)
    env_id = getattr(env_spec, "id", None) or type(getattr(env, "unwrapped", env)).__name__
    dt = getattr(getattr(env, "unwrapped", env), "dt", None)
    if dt is None:
        fps = (getattr(env, "metadata", None) or {}).get("render_fps")
        if not fps:
            raise ValueError(f"{env_id}: no control period (no `dt`, no metadata render_fps)")
        dt = 1.0 / float(fps)
    return task_spec_from_spaces(
        task_name(str(env_id)),
        env.observation_space,
        env.action_space,
        getattr(env_spec, "max_episode_steps", None),
        float(dt),
        reward,
        termination,
        angles,
        base_preset,
    )
