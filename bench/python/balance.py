"""Gymnasium tasks that end their own episodes, learned with nothing given but their id: how
long the episodes last under random actions, and how many steps of experience the planner
needs before its episodes last (the termination learned from the ``terminated`` flags, the
reward from the rewards sent).

For each ``--env``: ``--random`` episodes with uniformly random actions (the lengths a task
ends its early episodes at), then ``ebmpc.gym.learn(env, steps=--steps)`` with a local planner
on a fresh data directory and the planner's defaults unless ``--preset`` / ``--override`` say
otherwise. It prints every learned episode's length, the first episode that lasted
``--long`` steps (or ran to the task's time limit) and the experience stored before it, the
longest episode, and the learned termination's held-out accuracy at the last retraining::

    chrt --idle 0 .venv/bin/python bench/python/balance.py \\
        --env InvertedDoublePendulum-v5 --steps 5000

A benchmark, not a test: it asserts nothing.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, List, Optional

from ebmpc import EventTimeout, Planner
from ebmpc.events import ModelsUpdated, TerminationAccuracy
from ebmpc.gym import EpisodeResult, learn, parse_override


def random_lengths(env_id: str, episodes: int, seed: int) -> List[int]:
    """Lengths of ``episodes`` episodes of uniformly random actions."""
    import gymnasium

    env = gymnasium.make(env_id)
    env.action_space.seed(seed)
    lengths = []
    try:
        for e in range(episodes):
            env.reset(seed=seed + e)
            steps = 0
            while True:
                _, _, terminated, truncated, _ = env.step(env.action_space.sample())
                steps += 1
                if terminated or truncated:
                    break
            lengths.append(steps)
    finally:
        env.close()
    return lengths


def last_termination_accuracy(events: Any) -> Optional[TerminationAccuracy]:
    """The termination accuracy of the last ``ModelsUpdated`` among the events received."""
    accuracy = None
    while True:
        try:
            event = events.next(timeout=0.5)
        except EventTimeout:
            return accuracy
        if isinstance(event, ModelsUpdated) and event.termination_accuracy is not None:
            accuracy = event.termination_accuracy


def one(args: argparse.Namespace, env_id: str) -> None:
    lengths = random_lengths(env_id, args.random, args.seed)
    print(
        f"{env_id}: random actions, {len(lengths)} episodes: median {statistics.median(lengths)}"
        f" steps, longest {max(lengths)}",
        flush=True,
    )
    played: List[EpisodeResult] = []
    run = "balance"
    started = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="ebmpc-balance-bench-") as data:
        with Planner.local(Path(data)) as planner, planner.events(run) as events:
            learn(
                env_id, steps=args.steps, preset=args.preset, overrides=dict(args.override),
                planner=planner, run=run, seed=args.seed, mode=args.mode, progress=False,
                on_episode=played.append,
            )
            accuracy = last_termination_accuracy(events)
    minutes = (time.monotonic() - started) / 60
    steps = [r.steps for r in played]
    print(f"{env_id}: learned episodes' steps: {', '.join(map(str, steps))}")
    experience = 0
    first = None
    for r in played:
        if r.steps >= args.long or r.end == "time_limit":
            first = (r.episode, experience, r.steps)
            break
        experience += r.steps
    first_text = (
        f"first episode of {args.long}+ steps: episode {first[0]} ({first[2]} steps) after "
        f"{first[1]} steps of experience" if first else f"no episode of {args.long}+ steps"
    )
    accuracy_text = (
        f"termination accuracy {accuracy.accuracy:.2f}, recall {accuracy.recall:.2f} "
        f"({accuracy.terminations} ends in {accuracy.held_out} held-out transitions)"
        if accuracy else "no termination accuracy reported"
    )
    print(
        f"{env_id}: {len(played)} episodes, {sum(steps)} steps in {minutes:.1f} min; "
        f"{first_text}; longest {max(steps)}; last three {steps[-3:]}; {accuracy_text}",
        flush=True,
    )


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--env", nargs="+", default=["InvertedDoublePendulum-v5"],
        help="Gymnasium ids (InvertedDoublePendulum-v5)",
    )
    p.add_argument("--steps", type=int, default=5000, help="steps of experience (5000)")
    p.add_argument(
        "--random", type=int, default=20, help="episodes of random actions first (20)"
    )
    p.add_argument(
        "--long", type=int, default=200,
        help="an episode this long counts as staying up (200; or one that reaches the time limit)",
    )
    p.add_argument("--preset", default=None, help="planner preset (the planner's default)")
    p.add_argument(
        "--override", type=parse_override, action="append", default=[], metavar="KEY=VALUE",
        help="a preset field to change; repeatable",
    )
    p.add_argument("--mode", choices=("sync", "async"), default="sync", help="train mode (sync)")
    p.add_argument("--seed", type=int, default=0, help="seed (0)")
    args = p.parse_args()
    for env_id in args.env:
        one(args, env_id)
    return 0


if __name__ == "__main__":
    sys.exit(main())
