"""How far the ant's CEM gets when its model is the simulator itself.

The ant at paper sizes stays up but barely moves forward within 4,000 timesteps with any method
(docs/results.md, "Ant at 4,000 timesteps"). This separates the planner from the learned models:
the same CEM as the ant preset (population 500, 50 elites, 7 iterations, horizon 30 control
steps of 0.05 s, truncated Gaussian at ±2σ with the variance capped by the bounds, smoothing
0.1, warm start shifted by one step), scoring each candidate by rolling it out in MuJoCo from
the true current state (`mujoco.rollout`) instead of through a learned network. If this oracle
planner walks, the gap is in what the models learn from 4,000 transitions; if it does not, no
model could make this planner walk under this reward.

The task is sim-bridge's (sim-bridge/assets/ant.xml; reset and termination taken from
`ant_vs_gymnasium.py`, which mirrors them, the reward vectorised over candidates): reward `forward velocity − 0.5 ‖a‖² + 1` per step, the episode ends
when the torso height leaves [0.2, 1.0] m, and an imagined trajectory earns nothing after it
would have ended.

Needs the project's Python environment (`make python-env`):

    .venv/bin/python experiments/probes/ant_oracle_cem.py [--steps 200] [--seeds 2] [--threads 1]
"""

import argparse
import time

import mujoco
import numpy as np
from ant_vs_gymnasium import HEALTHY, MODEL, SUBSTEPS, reset  # the task as mirrored there
from mujoco import rollout

ACT, DT = 8, 0.05


def reward(forward_velocity, a):
    return forward_velocity - 0.5 * np.sum(a * a, axis=-1) + 1.0


class OracleCem:
    """The ant preset's CEM with MuJoCo as the model."""

    def __init__(self, m, horizon, population, elites, iterations, smoothing, threads, rng):
        self.m, self.h, self.pop, self.elites = m, horizon, population, elites
        self.iterations, self.smoothing, self.rng = iterations, smoothing, rng
        self.datas = [mujoco.MjData(m) for _ in range(threads)]
        self.mean = np.zeros((horizon, ACT))
        spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        self.spec = spec
        # Offsets of qpos and qvel in a full-physics state vector (time comes first).
        self.qpos_at = 1
        self.qvel_at = 1 + m.nq

    def returns(self, state, actions):
        """Return of each candidate (population × horizon × 8) rolled out from `state`."""
        controls = np.repeat(actions, SUBSTEPS, axis=1)  # one control per substep
        states, _ = rollout.rollout(self.m, self.datas, state[None, :], controls)
        after = states[:, SUBSTEPS - 1 :: SUBSTEPS, :]  # the state after each control step
        z = after[:, :, self.qpos_at + 2]
        vx = after[:, :, self.qvel_at]
        per_step = reward(vx, actions)
        healthy = (z >= HEALTHY[0]) & (z <= HEALTHY[1])
        # The step that leaves the healthy range still earns; nothing after it does.
        alive_before = np.concatenate(
            [np.ones((len(actions), 1), bool), np.cumprod(healthy, axis=1)[:, :-1].astype(bool)],
            axis=1,
        )
        return np.sum(per_step * alive_before, axis=1)

    def plan(self, state):
        mean = self.mean.copy()
        var = np.full_like(mean, 2.0 * 2.0 / 16.0)
        for _ in range(self.iterations):
            cap = np.minimum(((mean + 1.0) ** 2) / 4.0, ((1.0 - mean) ** 2) / 4.0)
            std = np.sqrt(np.minimum(var, cap))
            z = self.rng.standard_normal((self.pop, self.h, ACT))
            while True:  # truncated at ±2σ by redrawing
                out = np.abs(z) > 2.0
                if not out.any():
                    break
                z[out] = self.rng.standard_normal(out.sum())
            candidates = mean + std * z
            ret = self.returns(state, candidates)
            elite = candidates[np.argsort(ret)[-self.elites :]]
            mean = self.smoothing * mean + (1 - self.smoothing) * elite.mean(axis=0)
            var = self.smoothing * var + (1 - self.smoothing) * elite.var(axis=0)
        action = mean[0].copy()
        self.mean = np.concatenate([mean[1:], np.zeros((1, ACT))])
        return action


def episode(seed, steps, threads, population, iterations):
    m = mujoco.MjModel.from_xml_path(str(MODEL))
    rng = np.random.default_rng(seed)
    d = reset(m, rng)
    cem = OracleCem(m, 30, population, population // 10, iterations, 0.1, threads, rng)
    state = np.empty(mujoco.mj_stateSize(m, cem.spec))
    x0, ret, started = d.qpos[0], 0.0, time.perf_counter()
    for t in range(steps):
        mujoco.mj_getState(m, d, state, cem.spec)
        a = cem.plan(state)
        d.ctrl[:] = a
        for _ in range(SUBSTEPS):
            mujoco.mj_step(m, d)
        ret += float(reward(d.qvel[0], a))
        z = d.qpos[2]
        if (t + 1) % 50 == 0:
            print(
                f"  seed {seed} step {t + 1}: x {d.qpos[0] - x0:+.2f} m, return {ret:.1f}, "
                f"{(time.perf_counter() - started) / (t + 1):.2f} s per planned step",
                flush=True,
            )
        if not HEALTHY[0] <= z <= HEALTHY[1]:
            return t + 1, ret, d.qpos[0] - x0, "ended: torso left [0.2, 1.0] m"
    return steps, ret, d.qpos[0] - x0, "time limit of the probe"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=200, help="control steps per episode")
    ap.add_argument("--seeds", type=int, default=2, help="episodes, seeded 0, 1, ...")
    ap.add_argument("--threads", type=int, default=1, help="MuJoCo rollout threads")
    ap.add_argument("--population", type=int, default=500, help="CEM population (elites: a tenth)")
    ap.add_argument("--iterations", type=int, default=7, help="CEM iterations per plan")
    args = ap.parse_args()
    print(
        f"oracle CEM on {MODEL.name}: population {args.population}, "
        f"{args.iterations} iterations, horizon 30"
    )
    for seed in range(args.seeds):
        steps, ret, dx, end = episode(seed, args.steps, args.threads, args.population, args.iterations)
        print(
            f"seed {seed}: {steps} steps ({end}), return {ret:.1f} ({ret / steps:.2f} per step), "
            f"forward {dx:+.2f} m = {dx / (steps * DT):+.2f} m/s"
        )


if __name__ == "__main__":
    main()
