"""The Gymnasium driver: a planner learns a Gymnasium environment, episode by episode.

From Python, :func:`learn` (it starts a local planner unless it is given one)::

    from ebmpc.gym import learn
    results = learn("Pendulum-v1", episodes=10)
    print([r.episode_return for r in results])

From a shell, ``python -m ebmpc.gym`` is a thin wrapper around it::

    python -m ebmpc.gym --env InvertedPendulum-v5 --episodes 8 \\
        --reward-expression 1 --termination-expression 'abs(s_next[1]) > 0.2'

Without ``--connect`` the driver starts the ``planner-service`` installed with this package
(:meth:`ebmpc.Planner.local`) with its runs under the per-user data directory
(:func:`ebmpc.local.default_data_dir`, or ``--data-dir``) and stops it at the end; the run is
named after the environment unless ``--run`` names it, so the same command again resumes it.
With ``--connect`` it attaches to that planner instead.

Any environment with ``Box`` observation and action spaces works: the task spec comes from its
spaces (:mod:`ebmpc.gym_spec`), the reward is ``learned`` from the rewards this driver sends
with every step unless ``--reward-expression`` gives a formula, and the termination is
``learned`` from the episodes the environment ends unless ``--termination-expression`` gives
one. Gymnasium's two endings map onto the protocol's: ``terminated`` (the environment's own
rule fired: nothing follows the last state) ends the episode as ``terminated``, ``truncated``
(its time limit, or a wrapper's) as ``time_limit``; the planner stores both, a learned reward
trains on both, and a learned termination learns from the first which states end an episode
(so that falling costs a plan the rest of its horizon). ``--steps N`` budgets the experience
in environment steps instead of (or as well as) episodes: a task whose early episodes last 10
steps gets as much data as one whose episodes run to their limit. ``--num-envs N`` drives a
vector env of N copies as N agents of one run.

It prints one line per episode (return, steps, how it ended, milliseconds per action), a
progress line on stderr when that is a terminal, and exits with status 0, or with the status
of the error that stopped it (see :data:`EXIT_STATUS`).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from typing import Any, Callable, Dict, List, Mapping, Optional, Sequence, Tuple, Union

from .agent import Agent
from .errors import (
    ERROR_CLASSES,
    EbmpcError,
    PlannerError,
    PlannerNotFoundError,
    PlannerStartError,
    RefusedError,
)
from .gym_spec import task_spec_from_env
from .local import default_data_dir
from .planner import Planner
from .progress import Progress
from .wire import EpisodeEnd, TrainMode

#: Exit status when the environment cannot be made or learned (no Gymnasium, a space that is
#: not a vector ``Box``, an observation the wire cannot carry).
EXIT_ENVIRONMENT = 3
#: Exit status when this client failed: no planner answered, an action or an event did not
#: come in time, or an answer was not a message of this protocol.
EXIT_CLIENT = 4
#: Exit status when the local planner could not start (no binary, it exited at start, its port
#: was taken, another planner serves its data directory).
EXIT_LOCAL_PLANNER = 5
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
    #: The agent that played it (of a vector env: one per copy).
    agent: str = ""

    def line(self, with_agent: bool = False) -> str:
        """The driver's line for the episode (``with_agent``: prefixed with the agent)."""
        who = f"{self.agent} " if with_agent else ""
        return (
            f"{who}episode {self.episode}: return {self.episode_return:.2f}, steps {self.steps}, "
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
    """Asks one agent for actions, timing each and counting the planned ones."""

    def __init__(self, agent: Agent) -> None:
        self.agent = agent
        self.planned = 0
        self.first_ms = 0.0
        self.later_seconds = 0.0
        self.later = 0
        self._sent_at = 0.0
        self._first = True

    def submit(self, obs: List[float], reward: Optional[float] = None) -> None:
        self._sent_at = time.monotonic()
        self._first = reward is None
        self.agent.submit(obs, reward)

    def result(self) -> List[float]:
        action = self.agent.result()
        self._count(time.monotonic() - self._sent_at, self._first)
        return action

    def act(self, obs: List[float], reward: Optional[float] = None) -> List[float]:
        started = time.monotonic()
        action = self.agent.act(obs, reward)
        self._count(time.monotonic() - started, reward is None)
        return action

    def _count(self, seconds: float, first: bool) -> None:
        if first:
            self.first_ms = seconds * 1e3
        else:
            self.later_seconds += seconds
            self.later += 1
        self.planned += self.agent.last_stats.get("source") == "planned"


    def ms_per_action(self) -> float:
        return self.later_seconds * 1e3 / self.later if self.later else self.first_ms


class Budget:
    """How much experience to collect: ``episodes`` started and/or ``steps`` taken (``None``:
    no bound of that kind; at least one is given). A new episode starts while both leave
    room; an episode that has started always runs to its end, so the steps may overshoot by
    the last episodes' lengths."""

    def __init__(self, episodes: Optional[int], steps: Optional[int]) -> None:
        if episodes is None and steps is None:
            raise ValueError("give episodes, steps, or both")
        if episodes is not None and episodes < 1:
            raise ValueError("episodes must be at least 1")
        if steps is not None and steps < 1:
            raise ValueError("steps must be at least 1")
        self.episodes = episodes
        self.steps = steps

    def allows(self, started: int, steps: int) -> bool:
        """Whether another episode may start after ``started`` episodes and ``steps`` steps."""
        return (self.episodes is None or started < self.episodes) and (
            self.steps is None or steps < self.steps
        )


def run_episode(
    env: Any, agent: Agent, episode: int, seed: Optional[int], bar: Optional[Progress] = None
) -> EpisodeResult:
    """Plays one episode of ``env`` with the planner's actions, sending every step's reward
    (``bar``: a progress display that counts the steps)."""
    import numpy as np

    clock = _ActionClock(agent)
    obs, _ = env.reset(seed=seed)
    dtype, shape = env.action_space.dtype, env.action_space.shape
    action = clock.act(_finite(obs, "observation"))
    ret, steps = 0.0, 0
    while True:
        obs, reward, terminated, truncated, _ = env.step(np.asarray(action, dtype).reshape(shape))
        steps += 1
        if bar is not None:
            bar.step()
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
        clock.ms_per_action(), clock.first_ms, agent.name,
    )


def make_env(env_id: str, render: str = "none", num_envs: int = 1) -> Any:
    """``gymnasium.make(env_id)``, or with ``num_envs`` > 1 a vector env of that many copies
    (``gymnasium.make_vec``, stepped in this process); :class:`UndrivableEnvironment` if
    Gymnasium is missing or cannot make it."""
    try:
        import gymnasium
    except ImportError:
        raise UndrivableEnvironment(
            "gymnasium is not installed: pip install './python[gym]'"
        ) from None
    mode = None if render == "none" else render
    try:
        if num_envs > 1:
            return gymnasium.make_vec(
                env_id, num_envs=num_envs, vectorization_mode="sync", render_mode=mode
            )
        return gymnasium.make(env_id, render_mode=mode)
    except Exception as e:  # Gymnasium raises many kinds for an unknown or broken id
        raise UndrivableEnvironment(f"cannot make environment `{env_id}`: {e}") from None


def is_vector_env(env: Any) -> bool:
    """Whether ``env`` is a Gymnasium vector env (it has ``num_envs`` and single spaces)."""
    return hasattr(env, "num_envs") and hasattr(env, "single_action_space")


class _OneCopy:
    """What :func:`task_spec_from_env` reads of an environment, for one copy of a vector env."""

    def __init__(self, env: Any) -> None:
        self.spec = getattr(env, "spec", None)
        self.observation_space = env.single_observation_space
        self.action_space = env.single_action_space
        self.metadata = getattr(env, "metadata", None) or {}
        dts = None
        try:
            dts = env.get_attr("dt")
        except Exception:  # a vector env whose copies have no `dt`: render_fps then
            pass
        self.unwrapped = self
        if dts:
            self.dt = float(dts[0])


def _spec_of(env: Any, spec_args: Dict[str, Any]) -> Dict[str, Any]:
    try:
        return task_spec_from_env(_OneCopy(env) if is_vector_env(env) else env, **spec_args)
    except ValueError as e:
        env_id = getattr(getattr(env, "spec", None), "id", None) or type(env).__name__
        raise UndrivableEnvironment(f"{env_id}: {e}") from None


def learn(
    env: Any,
    episodes: Optional[int] = None,
    *,
    steps: Optional[int] = None,
    preset: Optional[str] = None,
    overrides: Optional[Mapping[str, Any]] = None,
    planner: Optional[Planner] = None,
    run: Optional[str] = None,
    reward: Optional[str] = None,
    termination: Optional[str] = None,
    angles: Sequence[int] = (),
    base_preset: Optional[str] = None,
    seed: Optional[int] = 0,
    mode: TrainMode = "sync",
    agent: Optional[str] = None,
    num_envs: int = 1,
    data_dir: Union[str, "os.PathLike[str]", None] = None,
    train_timeout: float = 600.0,
    progress: Optional[bool] = None,
    on_episode: Optional[Callable[[EpisodeResult], None]] = None,
    on_spec: Optional[Callable[[Dict[str, Any]], None]] = None,
) -> List[EpisodeResult]:
    """Learns a Gymnasium environment with an ebmpc planner; the episodes played, in the order
    they finished.

    ``env``: a Gymnasium id (made here, and closed at the end; ``num_envs`` > 1 makes a vector
    env of that many copies), an environment, or a vector environment (each copy an agent of
    the run, ``{agent}-{i}``: one replay buffer and one set of models, the planner serving
    their observations together). ``episodes``/``steps``: the budget, in episodes and/or
    environment steps over every copy (:class:`Budget`: new episodes start until either is
    reached; an episode that started runs to its end). The task spec comes from the spaces
    (:func:`ebmpc.gym_spec.task_spec_from_env`): ``reward``/``termination`` formulas
    (default: both learned, from the rewards and the ``terminated`` ends sent),
    ``angles``, ``base_preset``. ``preset``/``overrides``: the planner preset and fields of it to
    change. ``run``: the run's name (default: the environment's id, so that learning the same
    environment again continues its run). ``planner``: where to learn (default: a
    :meth:`Planner.local` on ``data_dir``, started and stopped here). ``agent``: the agent's
    name (default ``gym-0``), or of a vector env the prefix of its copies' (default ``gym``). ``seed``: the
    environment's first reset and the run's seed. ``mode``: ``sync`` (each agent's episode
    waits for the models retrained on its last) or ``async``. ``progress``: a progress line
    on stderr (``None``: when stderr is a terminal). ``on_episode`` is called with each
    episode's result as it finishes, ``on_spec`` with the derived task spec before attaching.

    Raises :class:`UndrivableEnvironment` for an environment that cannot be driven, the
    planner's errors as their :class:`~ebmpc.PlannerError`, and the local planner's start
    errors.
    """
    budget = Budget(episodes, steps)
    if num_envs < 1:
        raise ValueError("num_envs must be at least 1")
    if planner is not None and data_dir is not None:
        raise ValueError("data_dir is the local planner's: a given planner keeps its own")
    owned = isinstance(env, str)
    environment = make_env(env, num_envs=num_envs) if isinstance(env, str) else env
    try:
        spec = _spec_of(environment, dict(
            reward=reward, termination=termination, angles=angles, base_preset=base_preset,
        ))
        if on_spec is not None:
            on_spec(spec)
        run_name = run if run is not None else str(spec["name"])
        with contextlib.ExitStack() as stack:
            if planner is None:
                planner = stack.enter_context(
                    Planner.local(data_dir, train_timeout=train_timeout)
                )
            events = stack.enter_context(planner.events(run_name))
            bar = stack.enter_context(Progress(
                episodes, total_steps=steps, enabled=progress, events=events,
            ))
            results: List[EpisodeResult] = []

            def finished(result: EpisodeResult) -> None:
                results.append(result)
                bar.episode(result.episode_return)
                if on_episode is not None:
                    with bar.paused():
                        on_episode(result)

            if is_vector_env(environment):
                prefix = "gym" if agent is None else agent
                names = [f"{prefix}-{i}" for i in range(int(environment.num_envs))]
            else:
                names = ["gym-0" if agent is None else agent]
            agents = [
                stack.enter_context(_attach(
                    planner, run_name, spec, preset, dict(overrides or {}), name, mode, seed or 0,
                ))
                for name in names
            ]
            if is_vector_env(environment):
                _VectorDriver(environment, agents, bar, finished).run(budget, seed)
            else:
                taken = 0
                while budget.allows(len(results), taken):
                    # Seeded once: the environment's own generator then differs per episode,
                    # and the whole run is reproducible from the seed.
                    result = run_episode(
                        environment, agents[0], agents[0].episode,
                        seed if not results else None, bar,
                    )
                    taken += result.steps
                    finished(result)
            return results
    finally:
        if owned:
            environment.close()


#: How long :func:`learn` waits for an agent name that a closed agent held to be free again.
NAME_RELEASE_SECONDS = 10.0


def _attach(
    planner: Planner,
    run: str,
    spec: Dict[str, Any],
    preset: Optional[str],
    overrides: Dict[str, Any],
    name: str,
    mode: TrainMode,
    seed: int,
) -> Agent:
    """Attaches agent ``name``; while the planner still counts an agent of that name that was
    closed a moment ago as live (it learns of the departure from Zenoh's liveliness, shortly
    after), attaches again for up to :data:`NAME_RELEASE_SECONDS`."""
    deadline = time.monotonic() + NAME_RELEASE_SECONDS
    while True:
        try:
            return planner.attach(run, spec, preset, overrides, agent=name, mode=mode, seed=seed)
        except RefusedError as e:
            if "is attached to run" not in e.message or time.monotonic() > deadline:
                raise
            time.sleep(0.2)


class _VectorDriver:
    """Drives a Gymnasium vector env's copies as agents of one run, in lockstep.

    Every step sends the observations of all copies in an episode before it waits for their
    actions, so the planner plans them together. A copy's episode ends with its own last
    observation; the copy's reset (Gymnasium's autoreset, in any of its modes) starts the
    agent's next episode at step 0, so no transition across a reset is ever sent. Once the
    budget allows no new episode, a copy that finishes is left idle (its actions are ignored)
    until the others finish theirs: no episode is cut short.
    """

    def __init__(
        self,
        env: Any,
        agents: Sequence[Agent],
        bar: Progress,
        finished: Callable[[EpisodeResult], None],
    ) -> None:
        import numpy as np

        self.env = env
        self.agents = agents
        self.bar = bar
        self.finished = finished
        space = env.single_action_space
        self.dtype, self.shape = space.dtype, tuple(space.shape)
        # What an idle copy is sent: the middle of the action box (ignored all the same).
        self.idle_action = ((np.asarray(space.low) + np.asarray(space.high)) / 2).astype(
            self.dtype
        )
        # Gymnasium's AutoresetMode (an enum; its values are "NextStep", "SameStep",
        # "Disabled"); vector envs without the key autoreset on the next step.
        mode = (getattr(env, "metadata", None) or {}).get("autoreset_mode")
        self.autoreset: str = getattr(mode, "name", None) or {
            "SameStep": "SAME_STEP", "Disabled": "DISABLED",
        }.get(str(mode), "NEXT_STEP")

    def run(self, budget: Budget, seed: Optional[int]) -> None:
        import numpy as np

        n = len(self.agents)
        obs, _ = self.env.reset(seed=seed)
        started = 0
        taken = 0
        # Per copy: a clock while in an episode, None while idle or awaiting its reset.
        clocks: List[Optional[_ActionClock]] = [None] * n
        returns = [0.0] * n
        steps = [0] * n
        awaiting_reset = [False] * n

        def start(i: int, first_obs: Any) -> None:
            nonlocal started
            if not budget.allows(started, taken) or clocks[i] is not None:
                return
            started += 1
            clocks[i] = _ActionClock(self.agents[i])
            returns[i], steps[i] = 0.0, 0
            clocks[i].submit(_finite(first_obs, "observation"))  # type: ignore[union-attr]

        for i in range(n):
            start(i, obs[i])
        while any(c is not None for c in clocks) or any(awaiting_reset):
            actions = np.empty((n, *self.shape), self.dtype)
            for i, clock in enumerate(clocks):
                actions[i] = (
                    np.asarray(clock.result(), self.dtype).reshape(self.shape)
                    if clock is not None else self.idle_action
                )
            obs, rewards, terminated, truncated, info = self.env.step(actions)
            for i in range(n):
                if awaiting_reset[i]:
                    # NEXT_STEP autoreset: this step reset the copy; `obs[i]` is its first.
                    awaiting_reset[i] = False
                    start(i, obs[i])
                    continue
                clock = clocks[i]
                if clock is None:
                    continue
                reward = _finite([rewards[i]], "reward")[0]
                returns[i] += reward
                steps[i] += 1
                taken += 1
                self.bar.step()
                if not (terminated[i] or truncated[i]):
                    clock.submit(_finite(obs[i], "observation"), reward)
                    continue
                agent = self.agents[i]
                last = obs[i]
                if self.autoreset == "SAME_STEP":
                    last = info["final_obs"][i]
                end: EpisodeEnd = "terminated" if terminated[i] else "time_limit"
                episode = agent.episode
                agent.end(_finite(last, "observation"), reward, end)
                clocks[i] = None
                self.finished(EpisodeResult(
                    episode, returns[i], steps[i], end, clock.planned, agent.models_version,
                    clock.ms_per_action(), clock.first_ms, agent.name,
                ))
                if self.autoreset == "SAME_STEP":
                    start(i, obs[i])
                elif self.autoreset == "NEXT_STEP":
                    awaiting_reset[i] = True
            if self.autoreset == "DISABLED":
                # Every copy that ended, idle ones too, must be reset before its next step.
                done = np.logical_or(terminated, truncated)
                if done.any():
                    obs, _ = self.env.reset(options={"reset_mask": done})
                    for copy in np.flatnonzero(done):
                        start(int(copy), obs[copy])


def drive(args: argparse.Namespace) -> int:
    """Runs the driver with parsed arguments (a thin wrapper around :func:`learn`); the exit
    status."""
    env = make_env(args.env, args.render, args.num_envs)
    vector = args.num_envs > 1

    def show_spec(spec: Dict[str, Any]) -> None:
        if args.print_spec:
            print(json.dumps(spec, indent=2), flush=True)

    def show(result: EpisodeResult) -> None:
        print(result.line(with_agent=vector), flush=True)

    try:
        with contextlib.ExitStack() as stack:
            planner: Optional[Planner] = None
            if args.connect:
                planner = stack.enter_context(
                    Planner(connect=args.connect, train_timeout=args.train_timeout)
                )
            learn(
                env,
                args.episodes,
                steps=args.steps,
                preset=args.preset,
                overrides=dict(args.override),
                planner=planner,
                run=args.run,
                reward=args.reward_expression,
                termination=args.termination_expression,
                angles=args.angle,
                base_preset=args.base_preset,
                seed=args.seed,
                mode=args.mode,
                agent=args.agent,
                data_dir=args.data_dir,
                train_timeout=args.train_timeout,
                progress=False if args.no_progress else None,
                on_episode=show,
                on_spec=show_spec,
            )
        return 0
    finally:
        env.close()


def parser() -> argparse.ArgumentParser:
    """The command line of ``python -m ebmpc.gym``."""
    exits = ", ".join(f"{code} {status}" for code, status in EXIT_STATUS.items())
    p = argparse.ArgumentParser(
        prog="python -m ebmpc.gym",
        description="Learn a Gymnasium environment (Box observation and action spaces) with an "
        "ebmpc planner: the task spec comes from the environment's spaces, "
        "spec.max_episode_steps and dt; the reward is learned from the environment's rewards "
        "unless --reward-expression gives a formula. Without --connect it starts the planner "
        "installed with this package and keeps its runs in --data-dir.",
        epilog=f"Exit status: 0 done; 2 usage; {EXIT_ENVIRONMENT} the environment cannot be "
        f"driven; {EXIT_CLIENT} no planner, action or event in time, or an invalid answer; "
        f"{EXIT_LOCAL_PLANNER} the local planner could not start; a planner error by "
        f"its code: {exits}; {EXIT_UNKNOWN_CODE} another code.",
    )
    p.add_argument("--env", required=True, help="Gymnasium environment id (Pendulum-v1)")
    p.add_argument(
        "--run", default=None,
        help="the planner's run to create or resume (default: the environment's id, so the "
        "same command again resumes it)",
    )
    p.add_argument(
        "--episodes", type=int, default=None,
        help="episodes to play, over all copies with --num-envs (default 10 unless --steps "
        "is given)",
    )
    p.add_argument(
        "--steps", type=int, default=None,
        help="environment steps of experience to collect, over all copies: episodes start "
        "until this many steps are taken (and --episodes, if given, are played); an episode "
        "that started runs to its end",
    )
    p.add_argument(
        "--num-envs", type=int, default=1, metavar="N",
        help="copies of the environment in a Gymnasium vector env, each an agent of the run "
        "(AGENT-0 ... AGENT-N-1) feeding one replay buffer (default 1: a plain env)",
    )
    p.add_argument(
        "--connect", action="append", default=None,
        help="Zenoh endpoint of a running planner or router (tcp/127.0.0.1:7447); repeatable. "
        "Default: none; a local planner is started for this command and stopped at its end",
    )
    p.add_argument(
        "--data-dir", default=None, metavar="DIR",
        help="where the local planner keeps its runs (default $EBMPC_DATA_DIR, else the "
        f"per-user data directory, here {default_data_dir()}); not with --connect",
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
        help="formula over s_next that ends an imagined episode where it is not 0 (default: "
        "learned from the episodes the environment ends as terminated; 0 for none)",
    )
    p.add_argument(
        "--angle", type=int, action="append", default=[], metavar="INDEX",
        help="an observation dimension that is an angle (the model sees its sin and cos); "
        "repeatable",
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the environment and the run")
    p.add_argument(
        "--agent", default=None,
        help="this agent's name in the run (default gym-0; with --num-envs, the prefix of "
        "the copies' names: gym-0 ... gym-N-1)",
    )
    p.add_argument(
        "--mode", choices=("sync", "async"), default="sync",
        help="sync: each episode waits for the models retrained on the last (default); "
        "async: agents act on the previous models while the trainer works",
    )
    p.add_argument(
        "--render", choices=("none", "human", "rgb_array"), default="none",
        help="Gymnasium render mode (default none)",
    )
    p.add_argument(
        "--train-timeout", type=float, default=600.0, metavar="SECONDS",
        help="longest wait for an episode's first action, which waits for retraining (600)",
    )
    p.add_argument(
        "--no-progress", action="store_true",
        help="no progress line on stderr (drawn only when stderr is a terminal anyway)",
    )
    p.add_argument("--print-spec", action="store_true", help="print the derived task spec")
    return p


def main(argv: Optional[Sequence[str]] = None) -> int:
    """``python -m ebmpc.gym``: parses ``argv`` and runs the driver; the exit status."""
    p = parser()
    args = p.parse_args(argv)
    if args.episodes is None and args.steps is None:
        args.episodes = 10
    if args.episodes is not None and args.episodes < 1:
        p.error("--episodes must be at least 1")
    if args.steps is not None and args.steps < 1:
        p.error("--steps must be at least 1")
    if args.num_envs < 1:
        p.error("--num-envs must be at least 1")
    if args.connect and args.data_dir is not None:
        p.error("--data-dir is the local planner's: a planner of --connect keeps its own")
    try:
        return drive(args)
    except PlannerError as e:
        print(f"error: the planner refused: {e}", file=sys.stderr)
        return EXIT_STATUS.get(e.code, EXIT_UNKNOWN_CODE)
    except UndrivableEnvironment as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_ENVIRONMENT
    except (PlannerNotFoundError, PlannerStartError) as e:
        print(f"error: the local planner could not start: {e}", file=sys.stderr)
        return EXIT_LOCAL_PLANNER
    except (EbmpcError, TimeoutError) as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_CLIENT


if __name__ == "__main__":
    sys.exit(main())
