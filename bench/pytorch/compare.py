#!/usr/bin/env python3
"""ebmpc against PyTorch, side by side in one run: per planning call, median and best.

For each configuration (task, with and without DEEN), runs `planner-service bench plan` at every
inference precision it has (`auto`, the default, which measures the kernel paths and picks the
fastest; `bf16`; `f32`) and bench/pytorch/cem.py (the same batched CEM in PyTorch, f32 and bf16:
oneDNN multiplies bf16 on AMX tiles where the CPU has them), with the network sizes and CEM
settings that `bench plan` printed. The cells of a configuration run one after the other, and
with `--rounds` above 1 the whole set runs again in turn, so that every cell sees the same
changing load; each cell's figure is then the median of its rounds' medians and the best of
its bests. Prints a Markdown table labelled with the CPU (model, family/model), the date, the
commit, the load average and the oneDNN kernel PyTorch's bf16 products ran, then the ratios of
every configuration.

`--planner` may be given more than once as `LABEL=PATH` (e.g. `main=/tmp/planner-main
new=target/release/planner-service`): every binary's cells then run in the same turns, for a
before/after comparison on one machine. Run bench/pytorch/setup.sh once first. Example:

    cargo build --release -p planner-service --bin planner-service
    bench/pytorch/.venv/bin/python bench/pytorch/compare.py --planner target/release/planner-service
"""

import argparse
import datetime
import json
import os
import pathlib
import re
import statistics
import subprocess
import sys

HERE = pathlib.Path(__file__).resolve().parent
# (label, task, regularizer): every task cem.py implements, without and with DEEN.
CONFIGS = [
    ("cartpole", "cartpole", "none"),
    ("cartpole + DEEN", "cartpole", "deen"),
    ("half-cheetah", "halfcheetah", "none"),
    ("half-cheetah + DEEN", "halfcheetah", "deen"),
    ("ant", "ant", "none"),
    ("ant + DEEN", "ant", "deen"),
]
OUR_PRECISIONS = ("auto", "bf16", "f32")
TORCH_PRECISIONS = ("f32", "bf16")
# The presets' alpha, elites and CEM iterations (planner-service/src/config/preset.rs, Table 2):
# bench plan does not print them, and the cost does not depend on alpha.
TABLE2 = {"cartpole": (0.001, 40, 5), "halfcheetah": (0.05, 50, 5), "ant": (0.035, 50, 7)}


def cpu_name():
    info = {}
    for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
        key, _, value = line.partition(":")
        info.setdefault(key.strip(), value.strip())
    return (f"{info.get('model name', 'unknown CPU')} (family {info.get('cpu family', '?')}, "
            f"model {info.get('model', '?')})")


def load_average():
    return float(pathlib.Path("/proc/loadavg").read_text().split()[0])


def commit_of(path):
    """The commit of the binaries in folder `path`: its `COMMIT` file (as the experiments write
    beside binaries copied aside), else the commit of the git work tree it lies in (`-dirty`
    with uncommitted changes)."""
    if (path / "COMMIT").is_file():
        return (path / "COMMIT").read_text().strip()[:12]
    git = lambda *args: subprocess.run(["git", "-C", str(path), *args], capture_output=True, text=True)
    head = git("rev-parse", "--short", "HEAD")
    if head.returncode != 0:
        return "unknown"
    dirty = git("status", "--porcelain", "--untracked-files=no").stdout.strip()
    return head.stdout.strip() + ("-dirty" if dirty else "")


def expand(sizes):
    """`6→3×200→8` or `5→7→1` (bench plan's notation) as a list of layer sizes."""
    out = []
    for p in sizes.split("→"):
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
    optional = lambda pattern: (m.group(1) if (m := re.search(pattern, text)) else None)
    share = optional(r"threads ran (\d+)% of the time")
    cpu_ms = optional(r"CPU\s+([\d.]+) ms per call")
    return dict(
        text=text,
        median_ms=float(field(r"per call\s+([\d.]+) ms median")),
        best_ms=float(field(r"([\d.]+) ms best")),
        cpu_ms=float(cpu_ms) if cpu_ms else None,
        cpu_share=int(share) / 100 if share else None,
        dynamics=expand(field(r"dynamics\s+(\S+)")),
        energy=expand(field(r"energy\s+(\S+)")) if "energy " in text else None,
        horizon=int(field(r"horizon (\d+)")),
        population=int(field(r"population (\d+)")),
        precision=field(r"chunk\(s\), (\w+) inference"),
        kernels=optional(r"kernels\s+(.+)"),
        iterations=float(field(r"([\d.]+) iterations and")),
    )


def pytorch(python, task, shape, precision, calls, warmup, threads, env=None):
    alpha, elites, iterations = TABLE2[task]
    cmd = [python, str(HERE / "cem.py"), "--task", task, "--dynamics", ",".join(map(str, shape["dynamics"])),
           "--horizon", str(shape["horizon"]), "--population", str(shape["population"]),
           "--elites", str(elites), "--iterations", str(iterations), "--precision", precision,
           "--calls", str(calls), "--warmup", str(warmup), "--threads", str(threads), "--alpha", str(alpha)]
    if shape["energy"]:
        cmd += ["--energy", ",".join(map(str, shape["energy"]))]
    run = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env)
    return json.loads(run.stdout.strip().splitlines()[-1]), run.stdout


def onednn_kernels(python, task, shape, threads):
    """The oneDNN implementations PyTorch's bf16 products ran (one verbose call of cem.py)."""
    env = dict(os.environ, ONEDNN_VERBOSE="1")
    _, verbose = pytorch(python, task, shape, "bf16", 1, 0, threads, env)
    # onednn_verbose,v1,primitive,exec,cpu,matmul,<implementation>,... (on standard output)
    kinds = {line.split(",")[6] for line in verbose.splitlines()
             if line.startswith("onednn_verbose") and ",exec,cpu,matmul," in line}
    isa = next((line.split("isa:")[1].rstrip(",") for line in verbose.splitlines() if "isa:" in line), "?")
    return sorted(kinds), isa


def summarise(runs):
    """One cell over its rounds: median of the medians, best of the bests."""
    out = dict(runs[-1])
    out["median_ms"] = statistics.median(r["median_ms"] for r in runs)
    out["best_ms"] = min(r["best_ms"] for r in runs)
    out["rounds"] = [(r["median_ms"], r["best_ms"]) for r in runs]
    cpu = [r["cpu_ms"] for r in runs if r.get("cpu_ms") is not None]
    out["cpu_ms"] = statistics.median(cpu) if cpu else None
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--planner", action="append", default=None,
                   help="planner-service binary, or LABEL=PATH; repeat to compare binaries "
                        "(default: target/release/planner-service)")
    p.add_argument("--python", default=str(HERE / ".venv/bin/python"), help="Python with torch (setup.sh)")
    p.add_argument("--calls", type=int, default=20, help="timed planning calls per cell and round")
    p.add_argument("--warmup", type=int, default=3, help="untimed planning calls first, per cell and round")
    p.add_argument("--rounds", type=int, default=1, help="times every cell runs, in turns")
    p.add_argument("--threads", type=int, default=2, help="threads for both")
    p.add_argument("--only", default=None, help="run only the rows whose label is one of these (comma-separated)")
    p.add_argument("--json", default=None, help="also write every figure to this file")
    args = p.parse_args()

    planners = []
    for spec in args.planner or ["target/release/planner-service"]:
        label, _, path = spec.rpartition("=")
        planners.append((label or "ebmpc", path))
    configs = [c for c in CONFIGS if not args.only or c[0] in args.only.split(",")]
    if not configs:
        sys.exit(f"--only {args.only!r} names none of: {', '.join(c[0] for c in CONFIGS)}")

    load_start = load_average()
    rows = []
    for label, task, regularizer in configs:
        load_before = load_average()
        ours = {(who, pr): [] for who, _ in planners for pr in OUR_PRECISIONS}
        theirs = {pr: [] for pr in TORCH_PRECISIONS}
        shape = None
        for _ in range(args.rounds):
            for who, path in planners:
                for pr in OUR_PRECISIONS:
                    r = ebmpc(path, task, regularizer, pr, args.calls, args.warmup, args.threads)
                    ours[(who, pr)].append(r)
                    if pr == "f32" and shape is None:
                        shape = r
            for pr in TORCH_PRECISIONS:
                theirs[pr].append(pytorch(args.python, task, shape, pr, args.calls, args.warmup, args.threads)[0])
        ours = {k: summarise(v) for k, v in ours.items()}
        theirs = {k: summarise(v) for k, v in theirs.items()}
        rows.append(dict(label=label, task=task, regularizer=regularizer, ours=ours, theirs=theirs,
                         load=(load_before, load_average())))
        print(f"done: {label}", file=sys.stderr)

    kinds, isa = onednn_kernels(args.python, rows[0]["task"], rows[0]["ours"][(planners[0][0], "f32")],
                               args.threads)
    torch_version = rows[0]["theirs"]["f32"]["torch"]
    commits = ", ".join(f"{who} {commit_of(pathlib.Path(path).resolve().parent)}" for who, path in planners)
    print(f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, {cpu_name()}, "
          f"{os.cpu_count()} logical CPUs, load average {load_start:.1f} at the start; "
          f"{args.threads} threads, {args.rounds} round(s) of {args.calls} calls per cell after {args.warmup} "
          f"warm-up; ebmpc at {commits}; PyTorch {torch_version}, oneDNN ISA {isa!r}, bf16 matmuls ran "
          f"{', '.join(kinds) or '?'}. Per planning call: median ms (best ms).")
    print()
    ebmpc_cols = [(who, pr) for who, _ in planners for pr in OUR_PRECISIONS]
    name = lambda who, pr: f"{who} {pr}" if len(planners) > 1 or who != "ebmpc" else f"ebmpc {pr}"
    print("| per planning call | PyTorch f32 | PyTorch bf16 | "
          + " | ".join(name(*c) for c in ebmpc_cols) + " | kernels (auto) | load |")
    print("|---" * (4 + len(ebmpc_cols)) + "|---|")
    cell = lambda r: f"{r['median_ms']:.1f} ({r['best_ms']:.1f})"
    for row in rows:
        ours, theirs = row["ours"], row["theirs"]
        auto = ours[(planners[-1][0], "auto")]
        kernels = (auto.get("kernels") or "?").replace("dynamics ", "").replace("energy ", "")
        print(f"| {row['label']} | {cell(theirs['f32'])} | {cell(theirs['bf16'])} | "
              + " | ".join(cell(ours[c]) + ("" if ours[c]["precision"] == c[1] or c[1] == "auto"
                                            else f" (ran {ours[c]['precision']})") for c in ebmpc_cols)
              + f" | {kernels} | {row['load'][0]:.1f}–{row['load'][1]:.1f} |")
    print()
    print("Ratios of medians (PyTorch's time / ebmpc's: above 1, ebmpc is faster):")
    for row in rows:
        ours, theirs = row["ours"], row["theirs"]
        fastest = min(theirs.values(), key=lambda r: r["median_ms"])
        parts = []
        for who, _ in planners:
            a = ours[(who, "auto")]
            parts.append(f"{name(who, 'auto')} {fastest['median_ms'] / a['median_ms']:.2f}× PyTorch's faster "
                         f"({fastest['precision']}); bf16/bf16 "
                         f"{theirs['bf16']['median_ms'] / ours[(who, 'bf16')]['median_ms']:.2f}×, f32/f32 "
                         f"{theirs['f32']['median_ms'] / ours[(who, 'f32')]['median_ms']:.2f}×")
        print(f"- {row['label']}: " + "; ".join(parts))
    if len(planners) > 1:
        base, last = planners[0][0], planners[-1][0]
        print()
        print(f"{last} against {base}, ratios of medians (best) per precision:")
        for row in rows:
            ours = row["ours"]
            print(f"- {row['label']}: " + ", ".join(
                f"{pr} {ours[(base, pr)]['median_ms'] / ours[(last, pr)]['median_ms']:.2f}× "
                f"({ours[(base, pr)]['best_ms'] / ours[(last, pr)]['best_ms']:.2f}×)" for pr in OUR_PRECISIONS))
    if args.json:
        for row in rows:
            row["ours"] = {f"{who} {pr}": {k: v for k, v in r.items() if k != "text"}
                           for (who, pr), r in row["ours"].items()}
        pathlib.Path(args.json).write_text(json.dumps(
            dict(cpu=cpu_name(), torch=torch_version, onednn_isa=isa, onednn_bf16_matmul=kinds,
                 threads=args.threads, calls=args.calls, rounds=args.rounds, rows=rows), indent=1) + "\n")


if __name__ == "__main__":
    main()
