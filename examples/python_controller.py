#!/usr/bin/env python3
"""Drive an ebmpc run from Python: a controller in another language, speaking JSON over Zenoh.

The planner decodes a sample whose Zenoh encoding is ``application/json`` as JSON and answers
in JSON, so any Zenoh client can be an agent. This one simulates its own toy cart-pole (the
``cartpole`` task of the catalog: 4 observations ``[x, theta, x_dot, theta_dot]`` with
``theta = 0`` hanging down, 1 action: the force on the cart, within +-3) and plays a few short
episodes against a running planner:

    attach (query)   {prefix}/runs/{run}/attach                 -> accepted, or an error report
    step 0           {prefix}/runs/{run}/agents/{agent}/obs     -> action on .../act
    step t > 0       observation + reward of the last action    -> action on .../act
    last step        observation + reward + "end"               -> no action; episode stored
    status (query)   {prefix}/planners/{planner}/status         -> JSON; confirms what is stored

Anything the planner reports on ``.../error`` about our session ends the program with exit
status 1, as do a refused attach, a missing planner and a missing action; except a ``storage``
error (the planner could not store the step and kept nothing of it), after which the same
observation is sent again. Every observation carries the session token of our attach.

Requires the ``eclipse-zenoh`` package of the same minor version as the planner's zenoh (1.10):
``pip install 'eclipse-zenoh~=1.10.0'``. Example, against ``planner-service serve --listen
tcp/127.0.0.1:7447``:

    python3 examples/python_controller.py --connect tcp/127.0.0.1:7447 --episodes 3 --steps 40
"""

from __future__ import annotations

import argparse
import json
import math
import queue
import random
import sys
import time
from dataclasses import dataclass

try:
    import zenoh
except ImportError:  # pragma: no cover - exercised by hand
    sys.exit(
        "error: the `eclipse-zenoh` Python package is missing: pip install 'eclipse-zenoh~=1.10.0'"
    )

PROTOCOL_VERSION = 4
TASK = "cartpole"
OBS_DIM = 4
ACT_DIM = 1
ACTION_BOUND = 3.0
#: The catalog's episode length for cartpole: the planner refuses longer episodes' steps.
MAX_STEPS = 200
# Pause before sending again an observation the planner could not store (its disk is full).
STORAGE_RETRY_PAUSE = 1.0


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
# The agent's Zenoh side.
# --------------------------------------------------------------------------------------------


class Keys:
    """The key expressions of proto/src/keys.rs, for one prefix."""

    def __init__(self, prefix: str):
        self.prefix = prefix.strip("/")

    def agent(self, run: str, agent: str, channel: str) -> str:
        return f"{self.prefix}/runs/{run}/agents/{agent}/{channel}"

    def attach(self, run: str) -> str:
        return f"{self.prefix}/runs/{run}/attach"

    def planner_status(self, planner: str) -> str:
        return f"{self.prefix}/planners/{planner}/status"

    def agent_alive(self, run: str, agent: str) -> str:
        return f"{self.prefix}/alive/runs/{run}/agents/{agent}"


def zenoh_config(args: argparse.Namespace) -> zenoh.Config:
    """Explicit endpoints and no multicast scouting, as every ebmpc process (proto/src/session.rs)."""
    config = zenoh.Config.from_file(args.zenoh_config) if args.zenoh_config else zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    if args.connect:
        config.insert_json5("connect/endpoints", json.dumps(args.connect))
    return config


class Link:
    """One agent of one run: its subscriptions (declared before attaching, so no answer can
    arrive before we listen), its observation publisher and its liveliness token, by which the
    planner notices when this agent goes away."""

    def __init__(self, session: zenoh.Session, keys: Keys, run: str, agent: str):
        self.session, self.keys, self.run, self.agent = session, keys, run, agent
        # The run's ownership epoch at attach: actions of older epochs come from a planner that
        # lost the run (in a fleet of planners) and are ignored.
        self.epoch = 0
        # The session token of our attach (0: none yet): stamped on every observation, sent
        # again when re-attaching (so the planner knows it is us), and used to ignore reports
        # about someone else's observations under our agent name.
        self.session_token = 0
        # The last observation sent, to send again when the planner could not store it.
        self.last_sent: dict | None = None
        self.inbox: queue.Queue[tuple[str, dict]] = queue.Queue()
        self.token = session.liveliness().declare_token(keys.agent_alive(run, agent))
        self.subscribers = [
            session.declare_subscriber(keys.agent(run, agent, channel), self._receiver(channel))
            for channel in ("act", "error")
        ]
        self.publisher = session.declare_publisher(
            keys.agent(run, agent, "obs"),
            encoding=zenoh.Encoding.APPLICATION_JSON,
            # A control loop must not lose an observation to a full queue: block instead.
            congestion_control=zenoh.CongestionControl.BLOCK,
            express=True,
        )

    def _receiver(self, channel: str):
        def receive(sample: zenoh.Sample) -> None:
            try:
                message = json.loads(sample.payload.to_bytes())
            except ValueError as e:
                message = {"code": "malformed", "message": f"undecodable {channel}: {e}"}
                channel_seen = "error"
            else:
                channel_seen = channel
            if channel_seen == "error" and message.get("session") not in (None, self.session_token):
                return  # a refusal of another process's observation under our name
            self.inbox.put((channel_seen, message))

        return receive

    def attach(self, spec: dict, patience: float) -> dict:
        """Queries the attach key until a planner answers; returns the accepted run."""
        key = self.keys.attach(self.run)
        request = {"version": PROTOCOL_VERSION, "agent": self.agent, "spec": spec}
        if self.session_token:
            request["session"] = self.session_token
        payload = json.dumps(request).encode()
        deadline = time.monotonic() + patience
        while True:
            wait = max(0.5, min(5.0, deadline - time.monotonic()))
            # Every planner gets the query; only the run's owner answers.
            for reply in self.session.get(
                key, payload=payload, encoding=zenoh.Encoding.APPLICATION_JSON, timeout=wait,
                target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
            ):
                if reply.ok is None:
                    reason = reply.err.payload.to_string()
                    raise ControllerError(f"attach query on `{key}` failed: {reason}")
                answer = json.loads(reply.ok.payload.to_bytes())
                outcome = answer["outcome"]
                if "Rejected" in outcome:
                    raise ControllerError(f"attach refused: {describe(outcome['Rejected'])}")
                accepted = outcome["Accepted"]
                self.epoch = accepted.get("epoch", 0)
                self.session_token = accepted["session"]
                self._wait_until_planner_listens(deadline)
                return accepted
            if time.monotonic() + 0.5 >= deadline:
                raise ControllerError(f"no planner answered on `{key}` within {patience:.0f} s")
            time.sleep(0.5)

    def _wait_until_planner_listens(self, deadline: float) -> None:
        """The first observation must not be published before the planner's subscriber is known."""
        while not self.publisher.matching_status:
            if time.monotonic() >= deadline:
                raise ControllerError("the planner never subscribed to our observations")
            time.sleep(0.05)

    def send(self, observation: dict) -> None:
        observation = dict(observation, session=self.session_token)
        self.last_sent = observation
        self.publisher.put(json.dumps(observation).encode())

    def _resend_unstored(self, report: dict) -> bool:
        """A `storage` error means the planner kept nothing of our last observation and our
        session did not move on: send it again after a pause (as sim-bridge does). True if so."""
        if report.get("code") != "storage" or self.last_sent is None:
            return False
        print(f"the planner could not store a step, sending it again: {describe(report)}",
              file=sys.stderr)
        time.sleep(STORAGE_RETRY_PAUSE)
        self.publisher.put(json.dumps(self.last_sent).encode())
        return True

    def action(self, episode: int, step: int, timeout: float) -> dict:
        """Waits for the action answering (episode, step); any error report is fatal."""
        deadline = time.monotonic() + timeout
        while True:
            remaining = deadline - time.monotonic()
            try:
                channel, message = self.inbox.get(timeout=max(0.0, remaining))
            except queue.Empty:
                raise ControllerError(
                    f"no action for episode {episode} step {step} within {timeout:.0f} s"
                ) from None
            if channel == "error":
                if self._resend_unstored(message):
                    continue
                raise ControllerError(f"the planner reported: {describe(message)}")
            if message.get("epoch", 0) < self.epoch:
                print(f"ignoring an action of stale epoch {message.get('epoch')}", file=sys.stderr)
                continue
            if (message.get("episode"), message.get("step")) == (episode, step):
                return message
            # An answer to an earlier step cannot come after its successor's question was
            # asked; anything else is not ours to act on.
            print(f"ignoring an action for {message.get('episode')}/{message.get('step')}",
                  file=sys.stderr)

    def status(self, planner: str, timeout: float = 5.0) -> dict | None:
        """The planner's JSON status report, or None if it did not answer."""
        for reply in self.session.get(self.keys.planner_status(planner), timeout=timeout):
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_bytes())
        return None

    def drain_errors(self) -> None:
        """Fails on any error report still queued (e.g. about the last observation)."""
        while True:
            try:
                channel, message = self.inbox.get_nowait()
            except queue.Empty:
                return
            if channel == "error" and not self._resend_unstored(message):
                raise ControllerError(f"the planner reported: {describe(message)}")


def describe(report: dict) -> str:
    where = ""
    if report.get("episode") is not None:
        where = f" (episode {report['episode']}, step {report.get('step')})"
    return f"{report.get('code')}: {report.get('message')}{where}"


# --------------------------------------------------------------------------------------------
# The episode loop.
# --------------------------------------------------------------------------------------------


def validated_action(message: dict) -> float:
    action = message.get("action")
    if not isinstance(action, list) or len(action) != ACT_DIM:
        raise ControllerError(f"action of the wrong shape: {action!r}")
    value = float(action[0])
    if not math.isfinite(value) or abs(value) > ACTION_BOUND + 1e-4:
        raise ControllerError(f"action out of bounds: {value}")
    return value


def play_episode(link: Link, env: ToyCartpole, episode: int, args: argparse.Namespace) -> dict:
    """One episode; returns its summary."""
    obs = env.reset()
    total, planned, random_actions, models = 0.0, 0, 0, 0
    link.send({"version": PROTOCOL_VERSION, "episode": episode, "step": 0, "obs": obs})
    for step in range(args.steps):
        # The first action may wait for the trainer (sync mode retrains between episodes).
        timeout = args.train_timeout if step == 0 else args.action_timeout
        message = link.action(episode, step, timeout)
        stats = message.get("stats", {})
        if stats.get("source") == "planned":
            planned += 1
        else:
            random_actions += 1
        models = stats.get("models_version", models)
        obs, reward, applied = env.step(validated_action(message))
        total += reward
        observation = {
            "version": PROTOCOL_VERSION,
            "episode": episode,
            "step": step + 1,
            "obs": obs,
            "reward": reward,
            # What the actuator applied (clipped to its bounds): the planner stores this one.
            "applied": [applied],
        }
        if step + 1 == args.steps:
            observation["end"] = "time_limit"
        link.send(observation)
    return {
        "episode": episode,
        "return": total,
        "steps": args.steps,
        "planned": planned,
        "random": random_actions,
        "models_version": models,
    }


def wait_until_stored(link: Link, planner: str, run: str, agent: str, last: int,
                      at_least: int, timeout: float) -> dict:
    """Polls the planner's status until the run lists our last episode among its returns and
    counts at least `at_least` episodes (other agents of the run only add to that count)."""
    deadline = time.monotonic() + timeout
    while True:
        status = link.status(planner)
        for entry in (status or {}).get("runs", []):
            if entry.get("name") != run or entry.get("episodes", 0) < at_least:
                continue
            if any(a == agent and e == last for a, e, _ in entry.get("last_returns", [])):
                return entry
        if time.monotonic() >= deadline:
            raise ControllerError(
                f"the planner's status never listed episode {last} of run `{run}` as stored"
            )
        link.drain_errors()
        time.sleep(0.2)


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
    if not args.connect and not args.zenoh_config:
        args.connect = ["tcp/127.0.0.1:7447"]
    if not 1 <= args.steps <= MAX_STEPS:
        parser.error(f"--steps must be within 1..{MAX_STEPS}")
    if args.episodes < 1:
        parser.error("--episodes must be at least 1")
    return args


def run(args: argparse.Namespace) -> None:
    spec = {
        "task": TASK,
        "preset": args.preset,
        "overrides": dict(args.override),
        "mode": args.mode,
        "seed": args.seed,
    }
    env = ToyCartpole(random.Random(args.seed))
    session = zenoh.open(zenoh_config(args))
    try:
        link = Link(session, Keys(args.prefix), args.run, args.agent)
        accepted = link.attach(spec, args.attach_timeout)
        planner = accepted["planner_id"]
        if accepted["task"] != TASK:
            raise ControllerError(f"run `{args.run}` learns {accepted['task']}, not {TASK}")
        first = accepted["next_episode"]
        print(f"attached to run `{args.run}` on planner `{planner}` ({accepted['mode']} mode, "
              f"models v{accepted['models_version']}); episodes {first}..{first + args.episodes - 1}",
              flush=True)
        summaries = []
        for episode in range(first, first + args.episodes):
            summary = play_episode(link, env, episode, args)
            summaries.append(summary)
            print(f"episode {episode}: return {summary['return']:.3f} over {summary['steps']} "
                  f"steps ({summary['planned']} planned, {summary['random']} random actions; "
                  f"models v{summary['models_version']})", flush=True)
        stored = wait_until_stored(link, planner, args.run, args.agent, summaries[-1]["episode"],
                                   accepted["episodes_done"] + len(summaries), args.action_timeout)
        link.drain_errors()
        print(f"stored: run `{args.run}` holds {stored['episodes']} episodes, "
              f"{stored['transitions']} transitions, models v{stored['models_version']}")
        print("returns: " + " ".join(f"{s['return']:.3f}" for s in summaries), flush=True)
    finally:
        session.close()


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        run(args)
    except ControllerError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    except zenoh.ZError as e:
        print(f"error: zenoh: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
