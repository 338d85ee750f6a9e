#!/usr/bin/env python3
"""Drive an ebmpc run from Python with the `ebmpc` package (python/): a controller in another
language, speaking JSON over Zenoh.

It simulates its own toy cart-pole (the ``cartpole`` task of the catalog: 4 observations
``[x, theta, x_dot, theta_dot]`` with ``theta = 0`` hanging down, 1 action: the force on the
cart, within +-3) and plays a few short episodes against a running planner. The package keeps
the protocol's bookkeeping (session token, episode and step numbers, ownership epochs, sending
a step again after a ``storage`` error); any other error the planner reports ends the program
with exit status 1, as do a refused attach, a missing planner and a missing action.

Requires the package: ``pip install ./python`` (it brings ``eclipse-zenoh`` 1.10, the planner's
zenoh version). Example, against ``planner-service serve --listen tcp/127.0.0.1:7447``:

    python3 examples/python_controller.py --connect tcp/127.0.0.1:7447 --episodes 3 --steps 40
"""

from __future__ import annotations

import argparse
import json
import math
import random
import sys
from dataclasses import dataclass

try:
    import ebmpc
    import zenoh
except ImportError:  # pragma: no cover - exercised by hand
    sys.exit("error: the `ebmpc` Python package is missing: pip install ./python")

TASK = "cartpole"
OBS_DIM = 4
ACTION_BOUND = 3.0
#: The catalog's episode length for cartpole: the planner refuses longer episodes' steps.
MAX_STEPS = 200


class ControllerError(Exception):
    """Anything that ends the run early: printed, then exit status 1."""


# --------------------------------------------------------------------------------------------
# The toy environment: a cart with a point-mass pendulum, explicit Euler at the catalog's 0.04 s.
# --------------------------------------------------------------------------------------------


@dataclass
class ToyCartpole:
    """A cart (0.1 kg) on a rail with a 0.05 kg point mass on a 0.6 m massless pole.

    Not the MuJoCo model of sim-bridge (the planner learns whatever dynamics it is fed); the
    reward is the catalog's, so returns are comparable in scale: the pole tip near
    ``(0, 0.6)``, i.e. upright above the origin, scores 1 per step.
    """

    rng: random.Random
    cart_mass: float = 0.1
    pole_mass: float = 0.05
    pole_length: float = 0.6
    gravity: float = 9.81
    dt: float = 0.04
    substeps: int = 4

    def reset(self) -> list[float]:
        self.state = [self.rng.gauss(0.0, 0.05) for _ in range(OBS_DIM)]
        return list(self.state)

    def step(self, force: float) -> tuple[list[float], float, float]:
        """Applies `force`, clipped to the actuator's bounds, for one control step; returns the
        new observation, the reward and the force actually applied."""
        force = max(-ACTION_BOUND, min(ACTION_BOUND, force))
        x, theta, x_dot, theta_dot = self.state
        h = self.dt / self.substeps
        m, big_m, length, g = self.pole_mass, self.cart_mass, self.pole_length, self.gravity
        for _ in range(self.substeps):
            sin, cos = math.sin(theta), math.cos(theta)
            # Lagrange's equations of the cart and the pendulum, theta measured from hanging.
            x_acc = (force - m * sin * (g * cos + length * theta_dot**2)) / (big_m + m * sin**2)
            theta_acc = (cos * x_acc - g * sin) / length
            x_dot += h * x_acc
            theta_dot += h * theta_acc
            x += h * x_dot
            theta += h * theta_dot
        self.state = [x, theta, x_dot, theta_dot]
        return list(self.state), self.reward(force, self.state), force

    def reward(self, force: float, next_obs: list[float]) -> float:
        """The catalog's cartpole reward (proto/src/task/cartpole.rs)."""
        x, theta = next_obs[0], next_obs[1]
        tip_x = x - self.pole_length * math.sin(theta)
        tip_y = -self.pole_length * math.cos(theta)
        d2 = tip_x**2 + (tip_y - self.pole_length) ** 2
        return math.exp(-d2 / self.pole_length**2) - 0.01 * force**2


# --------------------------------------------------------------------------------------------
# The episode loop.
# --------------------------------------------------------------------------------------------


def checked_force(action: list[float]) -> float:
    if len(action) != 1:
        raise ControllerError(f"action of the wrong shape: {action!r}")
    value = action[0]
    if not math.isfinite(value) or abs(value) > ACTION_BOUND + 1e-4:
        raise ControllerError(f"action out of bounds: {value}")
    return value


def play_episode(agent: ebmpc.Agent, env: ToyCartpole, steps: int) -> dict:
    """One episode of `steps` transitions; returns its summary."""
    episode = agent.episode
    total, planned, random_actions, models = 0.0, 0, 0, 0
    action = agent.act(env.reset())
    for step in range(steps):
        if agent.last_stats.get("source") == "planned":
            planned += 1
        else:
            random_actions += 1
        models = agent.last_stats.get("models_version", models)
        obs, reward, applied = env.step(checked_force(action))
        total += reward
        # What the actuator applied (clipped to its bounds): the planner stores this one.
        if step + 1 == steps:
            agent.end(obs, reward, "time_limit", applied=[applied])
        else:
            action = agent.act(obs, reward, applied=[applied])
    return {"episode": episode, "return": total, "steps": steps, "planned": planned,
            "random": random_actions, "models_version": models}


def parse_override(text: str) -> tuple[str, object]:
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got `{text}`")
    try:
        return key, json.loads(value)
    except ValueError:
        return key, value


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description="Play toy cart-pole episodes against an ebmpc planner, in JSON over Zenoh."
    )
    parser.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                        help="Zenoh endpoint of the planner or a router, e.g. tcp/127.0.0.1:7447 "
                             "(repeatable; default tcp/127.0.0.1:7447 unless --zenoh-config)")
    parser.add_argument("--zenoh-config", metavar="FILE",
                        help="Zenoh JSON5 config to start from (TLS, a client mode, ...)")
    parser.add_argument("--prefix", default="ebmpc", help="key prefix shared with the planner")
    parser.add_argument("--run", default="python-demo", help="run to attach to (or create)")
    parser.add_argument("--agent", default="python-0", help="this agent's name in the run")
    parser.add_argument("--episodes", type=int, default=3, help="episodes to play")
    parser.add_argument("--steps", type=int, default=50,
                        help=f"steps per episode (at most the task's {MAX_STEPS})")
    parser.add_argument("--seed", type=int, default=0, help="seed of the run and of the toy")
    parser.add_argument("--preset", help="planner preset (cem, cem+dae, cem+deen, pets, pets+deen)")
    parser.add_argument("--mode", choices=["sync", "async"], default="sync",
                        help="sync: each episode waits for the models retrained on the last")
    parser.add_argument("--override", action="append", default=[], type=parse_override,
                        metavar="KEY=VALUE",
                        help="planner override of a new run, e.g. population=40 (repeatable)")
    parser.add_argument("--attach-timeout", type=float, default=60.0, metavar="SECONDS")
    parser.add_argument("--action-timeout", type=float, default=60.0, metavar="SECONDS")
    parser.add_argument("--train-timeout", type=float, default=600.0, metavar="SECONDS",
                        help="wait for the first action of an episode (retraining in sync mode)")
    args = parser.parse_args(argv)
    if not 1 <= args.steps <= MAX_STEPS:
        parser.error(f"--steps must be within 1..{MAX_STEPS}")
    if args.episodes < 1:
        parser.error("--episodes must be at least 1")
    return args


def run(args: argparse.Namespace) -> None:
    env = ToyCartpole(random.Random(args.seed))
    with ebmpc.Planner(args.connect, zenoh_config=args.zenoh_config, prefix=args.prefix,
                       attach_timeout=args.attach_timeout, action_timeout=args.action_timeout,
                       train_timeout=args.train_timeout) as planner:
        try:
            agent = planner.attach(args.run, TASK, args.preset, dict(args.override),
                                   agent=args.agent, mode=args.mode, seed=args.seed)
        except ebmpc.PlannerError as e:
            raise ControllerError(f"attach refused: {e}") from None
        with agent:
            if agent.task != TASK:
                raise ControllerError(f"run `{args.run}` learns {agent.task}, not {TASK}")
            first = agent.episode
            print(f"attached to run `{args.run}` on planner `{agent.planner_id}` ({agent.mode} "
                  f"mode, models v{agent.models_version}); episodes {first}..{first + args.episodes - 1}",
                  flush=True)
            summaries = []
            for _ in range(args.episodes):
                summary = play_episode(agent, env, args.steps)
                summaries.append(summary)
                print(f"episode {summary['episode']}: return {summary['return']:.3f} over "
                      f"{summary['steps']} steps ({summary['planned']} planned, {summary['random']} "
                      f"random actions; models v{summary['models_version']})", flush=True)
            # Every end() waited for the planner's word that the episode is stored.
            (stored,) = [r for r in planner.status(agent.planner_id)[0]["runs"]
                         if r["name"] == args.run]
        print(f"stored: run `{args.run}` holds {stored['episodes']} episodes, "
              f"{stored['transitions']} transitions, models v{stored['models_version']}")
        print("returns: " + " ".join(f"{s['return']:.3f}" for s in summaries), flush=True)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        run(args)
    except (ControllerError, ebmpc.EbmpcError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    except zenoh.ZError as e:
        print(f"error: zenoh: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
