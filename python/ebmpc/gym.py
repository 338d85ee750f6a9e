"""The Gymnasium driver: a planner learns a Gymnasium environment, episode by episode.

    python -m ebmpc.gym --env InvertedPendulum-v5 --run pendulum --episodes 8 \\
        --connect tcp/127.0.0.1:7447 --reward-expression 1 \\
        --termination-expression 'abs(s_next[1]) > 0.2'

Any environment with ``Box`` observation and action spaces works: the task spec comes from its
spaces (:mod:`ebmpc.gym_spec`), the reward is ``learned`` from the rewards this driver sends
with every step unless ``--reward-expression`` gives a formula. Gymnasium's two endings map onto
the protocol's: ``terminated`` (the environment's own rule fired: nothing follows the last
state) ends the episode as ``terminated``, ``truncated`` (its time limit, or a wrapper's) as
``time_limit``; the planner stores both, and a learned reward trains on both.

It prints one line per episode (return, steps, how it ended, milliseconds per action) and exits
with status 0, or with the status of the error that stopped it (see :data:`EXIT_STATUS`).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Sequence, Tuple

from .agent import Agent
from .errors import ERROR_CLASSES, EbmpcError, PlannerError
from .gym_spec import task_spec_from_env
from .planner import DEFAULT_ENDPOINT, Planner
from .wire import EpisodeEnd

#: Exit status when the environment cannot be made or learned (no Gymnasium, a space that is
#: not a vector ``Box``, an observation the wire cannot carry).
EXIT_ENVIRONMENT = 3
#: Exit status when this client failed: no planner answered, an action or an event did not
#: come in time, or an answer was not a message of this protocol.
EXIT_CLIENT = 4
#: Exit status of a planner error whose code this package does not know (a newer planner).
EXIT_UNKNOWN_CODE = 9
#: Exit status of each planner error code: 10 and up, in the wire's order of ``ErrorCode``.
EXIT_STATUS: Dict[str, int] = {code: 10 + i for i, code in enumerate(ERROR_CLASSES)}


class UndrivableEnvironment(Exception):
    """The environment cannot be driven (printed, then :data:`EXIT_ENVIRONMENT`)."""


@dataclass(frozen=True)
class EpisodeResult:
    """One episode as the environment scored it, and how its actions were made."""

    episode: int
    episode_return: float
    steps: int
    end: str
    #: Actions planned with the models (the others were random: exploration episodes).
    planned: int
    #: The version of the models behind the episode's last action.
    models_version: int
    #: Mean milliseconds from sending an observation to receiving its action, over the
    #: episode's steps after the first (the first waits for retraining in sync mode).
    ms_per_action: float
    #: Milliseconds the episode's first action took.
    first_action_ms: float

    def line(self) -> str:
        return (
            f"episode {self.episode}: return {self.episode_return:.2f}, steps {self.steps}, "
            f"end {self.end}, {self.ms_per_action:.2f} ms per action "
            f"(first {self.first_action_ms:.0f} ms; {self.planned} planned, "
            f"models v{self.models_version})"
        )


def parse_override(text: str) -> Tuple[str, Any]:
    """``key=value`` with the value read as JSON where it is JSON (``population=100``,
    ``sample_dynamics=true``, ``epoch_schedule={"drop_after": …}``) and as a string otherwise
    (``optimizer=icem``)."""
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise argparse.ArgumentTypeError(f"`{text}` is not key=value")
    try:
        value: Any = json.loads(raw)
    except ValueError:
        value = raw
    return key.strip(), value


def _finite(values: Any, what: str) -> List[float]:
    """``values`` (a NumPy array of any shape, or numbers) as a flat list of finite floats."""
    import numpy as np

    floats = [float(v) for v in np.ravel(values)]
    if not all(math.isfinite(v) for v in floats):
        raise UndrivableEnvironment(f"the environment returned a non-finite {what}: {floats}")
    return floats


class _ActionClock:
    """Asks the agent for actions, timing each and counting the planned ones."""

    def __init__(self, agent: Agent) -> None:
        self.agent = agent
        self.planned = 0
        self.first_ms = 0.0
        self.later_seconds = 0.0
        self.later = 0

    def act(self, obs: List[float], reward: Optional[float] = None) -> List[float]:
        started = time.monotonic()
        action = self.agent.act(obs, reward)
        seconds = time.monotonic() - started
        if reward is None:
            self.first_ms = seconds * 1e3
        else:
            self.later_seconds += seconds
            self.later += 1
        self.planned += self.agent.last_stats.get("source") == "planned"
        return action

    def ms_per_action(self) -> float:
        return self.later_seconds * 1e3 / self.later if self.later else self.first_ms


def run_episode(env: Any, agent: Agent, episode: int, seed: Optional[int]) -> EpisodeResult:
    """Plays one episode of ``env`` with the planner's actions, sending every step's reward."""
    import numpy as np

    clock = _ActionClock(agent)
    obs, _ = env.reset(seed=seed)
    dtype, shape = env.action_space.dtype, env.action_space.shape
    action = clock.act(_finite(obs, "observation"))
    ret, steps = 0.0, 0
    while True:
        obs, reward, terminated, truncated, _ = env.step(np.asarray(action, dtype).reshape(shape))
        steps += 1
        reward = _finite([reward], "reward")[0]
        ret += reward
        observed = _finite(obs, "observation")
        if terminated or truncated:
            end: EpisodeEnd = "terminated" if terminated else "time_limit"
            agent.end(observed, reward, end)
            break
        action = clock.act(observed, reward)
    return EpisodeResult(
        episode, ret, steps, end, clock.planned, agent.models_version,
        clock.ms_per_action(), clock.first_ms,
    )


def make_env(env_id: str, render: str) -> Any:
    try:
        import gymnasium
    except ImportError:
        raise UndrivableEnvironment(
            "gymnasium is not installed: pip install './python[gym]'"
        ) from None
    try:
        return gymnasium.make(env_id, render_mode=None if render == "none" else render)
    except Exception as e:  # Gymnasium raises many kinds for an unknown or broken id
        raise UndrivableEnvironment(f"cannot make environment `{env_id}`: {e}") from None


def drive(args: argparse.Namespace) -> int:
    """Runs the driver with parsed arguments; the exit status."""
    env = make_env(args.env, args.render)
    try:
        try:
            spec = task_spec_from_env(
                env,
                reward=args.reward_expression,
                termination=args.termination_expression,
                angles=args.angle,
                base_preset=args.base_preset,
            )
        except ValueError as e:
            raise UndrivableEnvironment(f"{args.env}: {e}") from None
        if args.print_spec:
            print(json.dumps(spec, indent=2))
        with Planner(connect=args.connect, train_timeout=args.train_timeout) as planner:
            with planner.attach(
                args.run,
                spec,
                args.preset,
                dict(args.override),
                agent=args.agent,
                mode=args.mode,
                seed=args.seed,
            ) as agent:
                for i in range(args.episodes):
                    # Seeded once: the environment's own generator then differs per episode,
                    # and the whole run is reproducible from --seed.
                    result = run_episode(env, agent, agent.episode, args.seed if i == 0 else None)
                    print(result.line(), flush=True)
        return 0
    finally:
        env.close()


def parser() -> argparse.ArgumentParser:
    exits = ", ".join(f"{code} {status}" for code, status in EXIT_STATUS.items())
    p = argparse.ArgumentParser(
        prog="python -m ebmpc.gym",
        description="Learn a Gymnasium environment (Box observation and action spaces) with an "
        "ebmpc planner: the task spec comes from the environment's spaces, "
        "spec.max_episode_steps and dt; the reward is learned from the environment's rewards "
        "unless --reward-expression gives a formula.",
        epilog=f"Exit status: 0 done; 2 usage; {EXIT_ENVIRONMENT} the environment cannot be "
        f"driven; {EXIT_CLIENT} no planner, action or event in time, or an invalid answer; a planner error by "
        f"its code: {exits}; {EXIT_UNKNOWN_CODE} another code.",
    )
    p.add_argument("--env", required=True, help="Gymnasium environment id (Pendulum-v1)")
    p.add_argument("--run", required=True, help="the planner's run to create or join")
    p.add_argument("--episodes", type=int, default=10, help="episodes to play (default 10)")
    p.add_argument(
        "--connect", action="append", default=None,
        help=f"Zenoh endpoint of the planner or router; repeatable (default {DEFAULT_ENDPOINT})",
    )
    p.add_argument("--preset", default=None, help="planner preset (method), e.g. cem+deen, pets")
    p.add_argument(
        "--override", type=parse_override, action="append", default=[], metavar="KEY=VALUE",
        help="a preset field to change (population=100); the value is JSON or a string; "
        "repeatable",
    )
    p.add_argument(
        "--base-preset", default=None,
        help="the catalog task whose paper sizes the run starts from (the spec's base_preset; "
        "the planner's default: cartpole)",
    )
    p.add_argument(
        "--reward-expression", default=None, metavar="FORMULA",
        help="reward formula over s, a, s_next (default: a learned reward); one that starts "
        "with '-' goes after '=': --reward-expression=-s[0]",
    )
    p.add_argument(
        "--termination-expression", default=None, metavar="FORMULA",
        help="formula over s_next that ends an imagined episode where it is not 0 "
        "(default: none; the environment still ends its own episodes)",
    )
    p.add_argument(
        "--angle", type=int, action="append", default=[], metavar="INDEX",
        help="an observation dimension that is an angle (the model sees its sin and cos); "
        "repeatable",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the environment and the run")
    p.add_argument("--agent", default="gym-0", help="this agent's name in the run (gym-0)")
    p.add_argument(
        "--mode", choices=("sync", "async"), default="sync",
        help="sync: each episode waits for the models retrained on the last (default)",
    )
    p.add_argument(
        "--render", choices=("none", "human", "rgb_array"), default="none",
        help="Gymnasium render mode (default none)",
    )
    p.add_argument(
        "--train-timeout", type=float, default=600.0, metavar="SECONDS",
        help="longest wait for an episode's first action, which waits for retraining (600)",
    )
    p.add_argument("--print-spec", action="store_true", help="print the derived task spec")
    return p


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = parser().parse_args(argv)
    if args.episodes < 1:
        parser().error("--episodes must be at least 1")
    try:
        return drive(args)
    except PlannerError as e:
        print(f"error: the planner refused: {e}", file=sys.stderr)
        return EXIT_STATUS.get(e.code, EXIT_UNKNOWN_CODE)
    except UndrivableEnvironment as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_ENVIRONMENT
    except (EbmpcError, TimeoutError) as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_CLIENT


if __name__ == "__main__":
    sys.exit(main())
