"""Transitions stored per wall-clock second when a Gymnasium vector env of N copies feeds one
run (``ebmpc.gym.learn(..., num_envs=N)``), against one env, side by side in one process.

Each configuration learns the same environment for the same number of episodes with its own
local planner (``Planner.local`` on a fresh data directory, the binary of ``$EBMPC_PLANNER_BIN``
or the installed one), so the figures differ only by the number of copies. A run first plays
``--warmup`` episodes with one env (the planner's random exploration, and its first models),
untimed; then the timed episodes, all planned, with N copies; then, untimed, ``--evaluate``
episodes with one env on the models retrained on every transition so far, from the same start
states in every configuration, to compare what the runs learned from the same number of
transitions. It prints, per configuration and repeat: the transitions stored, the seconds,
transitions per second, the mean return of the timed episodes and of the evaluation; then the
ratio of each N to N = 1, best and median over the repeats, and the evaluations' median::

    chrt --idle 0 .venv/bin/python bench/python/vector_envs.py --env Pendulum-v1 \\
        --episodes 16 --num-envs 1 8 --repeats 3

A benchmark, not a test: it asserts nothing about speed.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any, Dict, List, Tuple

from ebmpc import Planner
from ebmpc.events import ModelsUpdated, TrainingFailed, TrainingStarted
from ebmpc.gym import learn, parse_override


def wait_for_models(events: Any, transitions: int) -> None:
    """Waits for models retrained on at least ``transitions`` stored transitions."""
    covered = False
    while True:
        event = events.next()
        if isinstance(event, TrainingFailed):
            raise RuntimeError(f"a retraining failed: {event.message}")
        if isinstance(event, TrainingStarted):
            covered = event.transitions >= transitions
        elif isinstance(event, ModelsUpdated) and covered:
            return


def one(
    args: argparse.Namespace, num_envs: int, repeat: int
) -> Tuple[int, int, float, float, float]:
    """(transitions, of them planned, seconds, mean return of the timed episodes, mean return
    of the evaluation episodes or NaN without any). Repeat ``r`` runs with seed ``--seed + r``
    in every configuration."""
    run = f"bench-{num_envs}-{repeat}"
    seed = args.seed + repeat
    with tempfile.TemporaryDirectory(prefix="ebmpc-vector-bench-") as data:
        with Planner.local(Path(data)) as planner, planner.events(run, timeout=600) as events:
            common = dict(
                preset=args.preset, overrides=dict(args.override), planner=planner,
                run=run, mode=args.mode, progress=False,
            )
            # The warm-up plays under its own agent name: reusing it for the timed copies
            # would make their attach wait (seconds, timed) until the planner sees it leave.
            warmup = learn(args.env, args.warmup, seed=seed, agent="warmup", **common)
            # New agents wait for no retraining, so wait here for models trained on the whole
            # warm-up: else the timed copies would start with the run still exploring, their
            # actions random and almost free.
            warmup_steps = sum(r.steps for r in warmup)
            wait_for_models(events, warmup_steps)
            started = time.monotonic()
            results = learn(
                args.env, args.episodes, seed=seed, num_envs=num_envs,
                **common,
            )
            seconds = time.monotonic() - started
            evaluated = math.nan
            if args.evaluate:
                wait_for_models(events, warmup_steps + sum(r.steps for r in results))
                # The same start states in every configuration (the run's seed seeds the
                # first reset); a new agent plans at once.
                evaluation = learn(
                    args.env, args.evaluate, seed=seed, agent="evaluation",
                    **common,
                )
                evaluated = statistics.fmean(r.episode_return for r in evaluation)
    transitions = sum(r.steps for r in results)
    planned = sum(r.planned for r in results)
    mean_return = statistics.fmean(r.episode_return for r in results)
    return transitions, planned, seconds, mean_return, evaluated


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--env", default="Pendulum-v1", help="Gymnasium id (Pendulum-v1)")
    p.add_argument("--episodes", type=int, default=16, help="episodes per configuration (16)")
    p.add_argument(
        "--num-envs", type=int, nargs="+", default=[1, 8], help="copies to compare (1 8)"
    )
    p.add_argument(
        "--warmup", type=int, default=1, help="untimed episodes with one env first (1)"
    )
    p.add_argument("--repeats", type=int, default=3, help="runs of each configuration (3)")
    p.add_argument(
        "--evaluate", type=int, default=0,
        help="untimed episodes with one env after the timed ones, on models retrained on "
        "every transition (0: none)",
    )
    p.add_argument("--preset", default="cem", help="planner preset (cem)")
    p.add_argument(
        "--override", type=parse_override, action="append", default=[], metavar="KEY=VALUE",
        help="a preset field to change; repeatable",
    )
    p.add_argument("--mode", choices=("sync", "async"), default="sync", help="train mode (sync)")
    p.add_argument(
        "--seed", type=int, default=0, help="seed of the first repeat; the others follow (0)"
    )
    args = p.parse_args()
    rates: Dict[int, List[float]] = {n: [] for n in args.num_envs}
    evaluations: Dict[int, List[float]] = {n: [] for n in args.num_envs}
    for repeat in range(args.repeats):
        # Interleaved, so that a change of the machine's load falls on every configuration.
        for n in args.num_envs:
            transitions, planned, seconds, ret, evaluated = one(args, n, repeat)
            rates[n].append(transitions / seconds)
            evaluations[n].append(evaluated)
            evaluation = f", evaluation {evaluated:.1f}" if args.evaluate else ""
            print(
                f"num_envs {n} repeat {repeat}: {transitions} transitions ({planned} planned) "
                f"in {seconds:.1f} s, {transitions / seconds:.1f} per s, mean return {ret:.1f}"
                f"{evaluation}",
                flush=True,
            )
    base = rates[args.num_envs[0]]
    for n in args.num_envs[1:]:
        ratios = [r / b for r, b in zip(rates[n], base)]
        print(
            f"num_envs {n} / {args.num_envs[0]}: transitions per second x{max(ratios):.2f} best, "
            f"x{statistics.median(ratios):.2f} median over {len(ratios)} paired runs"
        )
    if args.evaluate:
        for n in args.num_envs:
            print(
                f"num_envs {n}: evaluation return median {statistics.median(evaluations[n]):.1f} "
                f"over {len(evaluations[n])} runs ({args.evaluate} episodes each)"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
