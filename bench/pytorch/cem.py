#!/usr/bin/env python3
"""The batched CEM planning call of `planner-service bench plan`, in plain PyTorch.

What a PyTorch user of the paper's method would write on this CPU: the whole population advances
one horizon step at a time through the dynamics MLP (swish hidden layers, outputs mean and
log-variance; the planner uses the mean) and, with DEEN, through the energy MLP (softplus hidden
layers, one output) on (s, a, s'); the return is the task's reward minus alpha times the energy;
PETS-style CEM (truncated Gaussian, variance capped by the bounds, smoothing 0.1, early stop on
min variance 0.001) refits to the elites. Sizes come from the command line, so that
`bench/pytorch/compare.py` can pass exactly the sizes `bench plan` printed. Weights are random:
the cost of a call does not depend on what the networks learned.

`--precision bf16` casts both networks and their inputs to torch.bfloat16 (oneDNN's bf16
GEMMs), as a PyTorch user would; f32 runs everything in float32. Prints one JSON line.
"""

import argparse
import json
import math
import statistics
import time

import torch

# Per task: observation and action sizes, action bound, the model's state features, how the
# next observation follows from the model's target, the reward and the termination (the same
# functions as proto/src/task/).
POLE_LENGTH = 0.6


def cartpole_features(s):
    return torch.cat([torch.sin(s[:, 1:2]), torch.cos(s[:, 1:2]), s[:, 0:1], s[:, 2:4]], dim=1)


def cartpole_reward(s, a, s1):
    tx = s1[:, 0] - POLE_LENGTH * torch.sin(s1[:, 1])
    ty = -POLE_LENGTH * torch.cos(s1[:, 1])
    d2 = tx * tx + (ty - POLE_LENGTH) ** 2
    return torch.exp(-d2 / POLE_LENGTH**2) - 0.01 * (a * a).sum(1)


def cheetah_features(s):
    return torch.cat([s[:, 1:2], torch.sin(s[:, 2:3]), torch.cos(s[:, 2:3]), s[:, 3:]], dim=1)


def cheetah_next(s, target):
    return torch.cat([target[:, 0:1], s[:, 1:] + target[:, 1:]], dim=1)


TASKS = {
    "cartpole": dict(
        obs=4,
        act=1,
        bound=3.0,
        features=cartpole_features,
        next=lambda s, t: s + t,
        reward=cartpole_reward,
        alive=None,
    ),
    "halfcheetah": dict(
        obs=18,
        act=6,
        bound=1.0,
        features=cheetah_features,
        next=cheetah_next,
        reward=lambda s, a, s1: s1[:, 0] - 0.1 * (a * a).sum(1),
        alive=None,
    ),
    "ant": dict(
        obs=27,
        act=8,
        bound=1.0,
        features=lambda s: s,
        next=lambda s, t: s + t,
        reward=lambda s, a, s1: s1[:, 13] - 0.5 * (a * a).sum(1) + 1.0,
        alive=lambda s1: (s1[:, 0] >= 0.2) & (s1[:, 0] <= 1.0),
    ),
}


def mlp(sizes, activation):
    layers = []
    for i, (a, b) in enumerate(zip(sizes, sizes[1:])):
        layers.append(torch.nn.Linear(a, b))
        if i < len(sizes) - 2:
            layers.append(activation())
    return torch.nn.Sequential(*layers)


def sizes(text):
    return [int(x) for x in text.split(",")]


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", choices=sorted(TASKS), default="cartpole", help="task whose reward is imagined")
    p.add_argument("--dynamics", type=sizes, required=True, help="dynamics layer sizes, e.g. 6,200,200,200,8")
    p.add_argument("--energy", type=sizes, default=None, help="DEEN layer sizes (none: no regulariser)")
    p.add_argument("--alpha", type=float, default=0.05, help="energy weight in the return")
    p.add_argument("--horizon", type=int, required=True, help="planning horizon")
    p.add_argument("--population", type=int, required=True, help="candidates per CEM iteration")
    p.add_argument("--elites", type=int, required=True, help="elites per refit")
    p.add_argument("--iterations", type=int, required=True, help="maximum CEM iterations")
    p.add_argument("--precision", choices=["f32", "bf16"], default="f32", help="inference number format")
    p.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: all cores)")
    p.add_argument("--calls", type=int, default=20, help="planning calls to time")
    p.add_argument("--warmup", type=int, default=3, help="untimed planning calls first")
    p.add_argument("--seed", type=int, default=0, help="seed of weights and sampling")
    args = p.parse_args()

    torch.manual_seed(args.seed)
    if args.threads:
        torch.set_num_threads(args.threads)
    task = TASKS[args.task]
    o, a = task["obs"], task["act"]
    dtype = torch.bfloat16 if args.precision == "bf16" else torch.float32
    dynamics = mlp(args.dynamics, torch.nn.SiLU).to(dtype).eval()
    energy = mlp(args.energy, torch.nn.Softplus).to(dtype).eval() if args.energy else None
    in_mean, in_std = torch.zeros(args.dynamics[0]), torch.ones(args.dynamics[0])
    out_mean, out_std = torch.zeros(o), torch.full((o,), 0.1)
    obs = torch.rand(o) * 2 - 1
    n, h = args.population, args.horizon
    lower, upper = -task["bound"], task["bound"]

    @torch.no_grad()
    def returns(actions):  # actions: n × h × a
        s = obs.expand(n, o).clone()
        ret = torch.zeros(n)
        alive = torch.ones(n, dtype=torch.bool)
        for t in range(h):
            u = actions[:, t, :]
            x = (torch.cat([task["features"](s), u], dim=1) - in_mean) / in_std
            target = dynamics(x.to(dtype)).float()[:, :o] * out_std + out_mean
            s1 = task["next"](s, target)
            r = task["reward"](s, u, s1)
            if energy is not None:
                e = energy(torch.cat([s, u, s1], dim=1).to(dtype)).float()[:, 0]
                r = r - args.alpha * e
            ret += torch.where(alive, r, torch.zeros_like(r))
            if task["alive"] is not None:
                alive &= task["alive"](s1)
            s = s1
        return torch.nan_to_num(ret, nan=-math.inf, posinf=-math.inf)

    mean = torch.zeros(h, a)

    def plan():
        nonlocal mean
        var = torch.full((h, a), (upper - lower) ** 2 / 16)
        iterations = 0
        while iterations < args.iterations and (iterations == 0 or var.max() > 1e-3):
            capped = torch.minimum(torch.minimum((mean - lower) ** 2 / 4, (upper - mean) ** 2 / 4), var)
            # Draws beyond ±2σ are folded back: the cost of truncation, not its exact distribution
            # (the timing does not depend on it).
            z = torch.fmod(torch.randn(n, h, a), 2.0)
            samples = (mean + capped.sqrt() * z).clamp(lower, upper)
            elite = samples[torch.topk(returns(samples), args.elites).indices]
            mean = 0.1 * mean + 0.9 * elite.mean(0)
            var = 0.1 * var + 0.9 * elite.var(0, unbiased=False)
            iterations += 1
        action = mean[0].clone()
        mean = torch.cat([mean[1:], torch.zeros(1, a)])
        return action, iterations

    for _ in range(args.warmup):
        plan()
    times, iterations = [], 0
    for _ in range(args.calls):
        start = time.perf_counter()
        _, it = plan()
        times.append((time.perf_counter() - start) * 1e3)
        iterations += it
    print(
        json.dumps(
            dict(
                task=args.task,
                precision=args.precision,
                threads=torch.get_num_threads(),
                torch=torch.__version__,
                median_ms=statistics.median(times),
                best_ms=min(times),
                mean_iterations=iterations / args.calls,
            )
        )
    )


if __name__ == "__main__":
    main()
