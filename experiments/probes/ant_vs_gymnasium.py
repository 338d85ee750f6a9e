"""Our ant against Gymnasium's Ant-v5 under random actions: episode lengths and returns.

An independent check that sim-bridge's ant (sim-bridge/assets/ant.xml with the task's reset,
reward and termination, mirrored here) is the environment the paper used. Both run the same
protocol: uniform random actions in [-1, 1]^8, episodes of at most 1,000 control steps of
0.05 s, ended when the torso height leaves [0.2, 1.0] m. For each it prints the episode
length (mean, median, quartiles, how many reach the time limit, what ended the others) and the
return, and for each statistic the difference of the means with a 95 % bootstrap interval.

Returns are compared as each task defines them and on a common footing:
- ours: `forward velocity − 0.5 ‖a‖² + 1` per step (proto's ant reward; the forward velocity is
  the torso's x velocity after the step);
- Ant-v5: its reward, and its reward without the contact cost (`reward_contact` in its info),
  which is what MBPO's and the paper's ant paid: their mujoco-py ≥ 2.0 reported zero contact
  forces (Gymnasium's documentation notes this), and the truncated observation has none.

Needs the project's Python environment (`make python-env`: gymnasium[mujoco]):

    .venv/bin/python experiments/probes/ant_vs_gymnasium.py [--episodes 200] [--csv FILE] [--model XML]
"""

import argparse
import pathlib

import gymnasium as gym
import mujoco
import numpy as np

MODEL = pathlib.Path(__file__).resolve().parents[2] / "sim-bridge" / "assets" / "ant.xml"
HEALTHY = (0.2, 1.0)
SUBSTEPS, EPISODE, NOISE = 5, 1000, 0.1


def ended_by(z, steps):
    if steps >= EPISODE and HEALTHY[0] <= z <= HEALTHY[1]:
        return "time limit"
    return "above 1 m" if z > HEALTHY[1] else "below 0.2 m"


def reset(m, rng):
    """sim-bridge's ant reset (its Rust code, mirrored): uniform noise on qpos (the torso's
    quaternion renormalised), Gaussian on qvel. Returns the data."""
    d = mujoco.MjData(m)
    qpos = m.qpos0 + rng.uniform(-NOISE, NOISE, m.nq)
    qpos[3:7] /= np.linalg.norm(qpos[3:7])
    d.qpos[:] = qpos
    d.qvel[:] = rng.normal(0.0, NOISE, m.nv)
    mujoco.mj_forward(m, d)
    return d


def ours(seed, model=MODEL):
    """One random-action episode of sim-bridge's ant task (its Rust code, mirrored)."""
    m = mujoco.MjModel.from_xml_path(str(model))
    rng = np.random.default_rng(seed)
    d = reset(m, rng)
    ret, steps = 0.0, 0
    while steps < EPISODE:
        a = rng.uniform(-1.0, 1.0, 8)
        d.ctrl[:] = a
        for _ in range(SUBSTEPS):
            mujoco.mj_step(m, d)
        steps += 1
        ret += d.qvel[0] - 0.5 * float(a @ a) + 1.0
        z = d.qpos[2]
        if not HEALTHY[0] <= z <= HEALTHY[1]:
            break
    return steps, ret, ret, ended_by(d.qpos[2], steps)


def gymnasium_ant(seed):
    """One random-action episode of Gymnasium's Ant-v5 (defaults)."""
    env = gym.make("Ant-v5", max_episode_steps=EPISODE)
    env.reset(seed=seed)
    rng = np.random.default_rng(10_000 + seed)
    ret = ret_no_contact = 0.0
    steps = 0
    while True:
        a = rng.uniform(-1.0, 1.0, 8)
        _, r, terminated, truncated, info = env.step(a)
        steps += 1
        ret += r
        ret_no_contact += r - info["reward_contact"]
        if terminated or truncated:
            break
    z = env.unwrapped.data.qpos[2]
    env.close()
    return steps, ret, ret_no_contact, ended_by(z, steps)


def bootstrap_diff(a, b, rng, n=10_000):
    """95 % bootstrap interval of mean(a) − mean(b)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    diffs = [
        rng.choice(a, a.size).mean() - rng.choice(b, b.size).mean() for _ in range(n)
    ]
    return np.percentile(diffs, [2.5, 97.5])


def describe(name, runs):
    lengths = np.array([r[0] for r in runs])
    returns = np.array([r[1] for r in runs])
    no_contact = np.array([r[2] for r in runs])
    causes = {}
    for r in runs:
        causes[r[3]] = causes.get(r[3], 0) + 1
    q1, med, q3 = np.percentile(lengths, [25, 50, 75])
    print(
        f"{name:<8} episodes {len(runs)}: length mean {lengths.mean():.0f} ± {lengths.std(ddof=1):.0f}, "
        f"median {med:.0f} [{q1:.0f}, {q3:.0f}], min {lengths.min()}, "
        f"ended by {', '.join(f'{k} {v}' for k, v in sorted(causes.items()))}"
    )
    print(
        f"{'':<8} return mean {returns.mean():.1f} ± {returns.std(ddof=1):.1f}, "
        f"without contact cost {no_contact.mean():.1f} ± {no_contact.std(ddof=1):.1f}, "
        f"per step {no_contact.sum() / lengths.sum():.3f}"
    )
    return lengths, no_contact


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--csv", type=pathlib.Path, help="write every episode here")
    parser.add_argument(
        "--model", type=pathlib.Path, default=MODEL, help="an ant MJCF other than sim-bridge's"
    )
    args = parser.parse_args()
    print(f"mujoco {mujoco.__version__}, gymnasium {gym.__version__}, model {args.model.name}")
    mine = [ours(s, args.model) for s in range(args.episodes)]
    theirs = [gymnasium_ant(s) for s in range(args.episodes)]
    l_ours, r_ours = describe("ours", mine)
    l_gym, r_gym = describe("Ant-v5", theirs)
    rng = np.random.default_rng(0)
    lo, hi = bootstrap_diff(l_ours, l_gym, rng)
    print(f"length: ours − Ant-v5 = {l_ours.mean() - l_gym.mean():.0f}, 95 % interval [{lo:.0f}, {hi:.0f}]")
    lo, hi = bootstrap_diff(r_ours, r_gym, rng)
    print(
        f"return without contact cost: ours − Ant-v5 = {r_ours.mean() - r_gym.mean():.1f}, "
        f"95 % interval [{lo:.1f}, {hi:.1f}]"
    )
    if args.csv:
        with open(args.csv, "w") as f:
            f.write("env,seed,steps,return,return_without_contact_cost,ended_by\n")
            for name, runs in (("ours", mine), ("Ant-v5", theirs)):
                for seed, (steps, ret, ret_nc, cause) in enumerate(runs):
                    f.write(f"{name},{seed},{steps},{ret:.4f},{ret_nc:.4f},{cause}\n")


if __name__ == "__main__":
    main()
