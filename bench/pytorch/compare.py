#!/usr/bin/env python3
"""ebmpc against PyTorch, side by side in one run: per planning call, median and best.

For each configuration, runs `planner-service bench plan` (bf16 and f32) and bench/pytorch/cem.py
(f32 and bf16) one after the other, with the network sizes and CEM settings that `bench plan`
printed, and prints a Markdown table dated and labelled with the CPU. Run bench/pytorch/setup.sh
once first. Example (release binary, as the README's table was made):

    cargo build --release -p planner-service
    bench/pytorch/.venv/bin/python bench/pytorch/compare.py --planner target/release/planner-service
"""

import argparse
import datetime
import json
import pathlib
import re
import subprocess
import sys

HERE = pathlib.Path(__file__).resolve().parent
# (label, task, regularizer): the rows of the README's table.
CONFIGS = [
    ("cartpole", "cartpole", "none"),
    ("cartpole + DEEN", "cartpole", "deen"),
    ("half-cheetah", "halfcheetah", "none"),
    ("half-cheetah + DEEN", "halfcheetah", "deen"),
    ("ant + DEEN", "ant", "deen"),
]


def cpu_name():
    info = {}
    for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
        key, _, value = line.partition(":")
        info.setdefault(key.strip(), value.strip())
    return f"{info.get('model name', 'unknown CPU')} (family {info.get('cpu family', '?')}, model {info.get('model', '?')})"


def expand(sizes):
    """`6→3×200→8` or `5→7→1` (bench plan's notation) as a list of layer sizes."""
    parts = sizes.split("→")
    out = []
    for p in parts:
        if "×" in p:
            count, width = p.split("×")
            out += [int(width)] * int(count)
        else:
            out.append(int(p))
    return out


def ebmpc(planner, task, regularizer, precision, calls, warmup, threads):
    cmd = [planner, "bench", "plan", "--task", task, "--regularizer", regularizer,
           "--precision", precision, "--iterations-to-time", str(calls), "--warmup", str(warmup),
           "--threads", str(threads)]
    text = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    field = lambda pattern: re.search(pattern, text).group(1)
    return dict(
        text=text,
        median_ms=float(field(r"per plan\s+([\d.]+) ms median")),
        best_ms=float(field(r"([\d.]+) ms best")),
        dynamics=expand(field(r"dynamics\s+(\S+)")),
        energy=expand(field(r"energy\s+(\S+)")) if "energy " in text else None,
        horizon=int(field(r"horizon (\d+)")),
        population=int(field(r"population (\d+)")),
        precision=field(r"chunk\(s\), (\w+) inference"),
        iterations=float(field(r"([\d.]+) iterations and")),
    )


def pytorch(python, task, shape, alpha, elites, iterations, precision, calls, warmup, threads):
    cmd = [python, str(HERE / "cem.py"), "--task", task, "--dynamics", ",".join(map(str, shape["dynamics"])),
           "--horizon", str(shape["horizon"]), "--population", str(shape["population"]),
           "--elites", str(elites), "--iterations", str(iterations), "--precision", precision,
           "--calls", str(calls), "--warmup", str(warmup), "--threads", str(threads), "--alpha", str(alpha)]
    if shape["energy"]:
        cmd += ["--energy", ",".join(map(str, shape["energy"]))]
    return json.loads(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout)


# The presets' alpha, elites and CEM iterations (planner-service/src/config/preset.rs, Table 2):
# bench plan does not print them, and the cost does not depend on alpha.
TABLE2 = {"cartpole": (0.001, 40, 5), "halfcheetah": (0.05, 50, 5), "ant": (0.035, 50, 7)}


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--planner", default="target/release/planner-service", help="planner-service binary")
    p.add_argument("--python", default=str(HERE / ".venv/bin/python"), help="Python with torch (setup.sh)")
    p.add_argument("--calls", type=int, default=20, help="timed planning calls per cell")
    p.add_argument("--warmup", type=int, default=3, help="untimed planning calls first, per cell")
    p.add_argument("--threads", type=int, default=2, help="threads for both")
    p.add_argument("--only", default=None, help="run only the rows whose label is one of these (comma-separated)")
    args = p.parse_args()

    rows = []
    for label, task, regularizer in CONFIGS:
        if args.only and label not in args.only.split(","):
            continue
        alpha, elites, iterations = TABLE2[task]
        ours = {pr: ebmpc(args.planner, task, regularizer, pr, args.calls, args.warmup, args.threads)
                for pr in ("bf16", "f32")}
        shape = ours["f32"]
        theirs = {pr: pytorch(args.python, task, shape, alpha, elites, iterations, pr, args.calls, args.warmup,
                              args.threads)
                  for pr in ("f32", "bf16")}
        rows.append((label, ours, theirs))
        print(f"done: {label}", file=sys.stderr)

    torch_version = next(iter(rows))[2]["f32"]["torch"] if rows else "?"
    print(f"{datetime.date.today()}, {cpu_name()}, {args.threads} threads, {args.calls} calls per cell, "
          f"PyTorch {torch_version}; per planning call: median ms (best ms)")
    print()
    print("| per planning call | PyTorch f32 | PyTorch bf16 | ebmpc bf16 | ebmpc f32 | CEM iterations (ebmpc / PyTorch) |")
    print("|---|---|---|---|---|---|")
    for label, ours, theirs in rows:
        cell = lambda r: f"{r['median_ms']:.1f} ({r['best_ms']:.1f})"
        bf16 = ours["bf16"]
        bf16_label = cell(bf16) if bf16["precision"] == "bf16" else cell(bf16) + " (ran f32)"
        print(f"| {label} | {cell(theirs['f32'])} | {cell(theirs['bf16'])} | {bf16_label} | {cell(ours['f32'])} "
              f"| {ours['f32']['iterations']:.1f} / {theirs['f32']['mean_iterations']:.1f} |")
    print()
    for label, ours, theirs in rows:
        best = min(theirs["f32"]["median_ms"], theirs["bf16"]["median_ms"])
        print(f"{label}: ebmpc bf16 is {best / ours['bf16']['median_ms']:.2f}× PyTorch's faster precision (medians)")


if __name__ == "__main__":
    main()
