"""Why ant episodes are short: random actions on our ant MJCF, and what ends each episode.

Runs the sim-bridge's ant model (sim-bridge/assets/ant.xml) under uniform random actions in
[-1, 1] with the task's control step (five 0.01 s steps) and gym's start noise on the joint angles and
velocities (the simulator also perturbs the torso's pose), and prints, per
seed, the step at which the torso height left the healthy band [0.2, 1.0] (proto's
`HEALTHY_HEIGHT`), the height there and the torso's up-axis z component (-1: on its back).
A diagnostic for the ant results (docs/results.md), not part of the service; it needs the MuJoCo Python
bindings of the version the project pins:

    python3 -m venv /tmp/mjv && /tmp/mjv/bin/pip install mujoco==3.17.0 numpy
    /tmp/mjv/bin/python experiments/probes/ant_random_episodes.py
"""

import pathlib

import mujoco
import numpy as np

MODEL = pathlib.Path(__file__).resolve().parents[2] / "sim-bridge" / "assets" / "ant.xml"
HEALTHY = (0.2, 1.0)
SUBSTEPS, EPISODE = 5, 1000

m = mujoco.MjModel.from_xml_path(str(MODEL))
d = mujoco.MjData(m)
print("seed  steps  torso_z  up_z  ended_by")
for seed in range(20):
    rng = np.random.default_rng(seed)
    mujoco.mj_resetData(m, d)
    d.qpos[7:] += rng.uniform(-0.1, 0.1, 8)
    d.qvel[:] = rng.normal(0.0, 0.1, m.nv)
    ended = "time limit"
    for t in range(1, EPISODE + 1):
        d.ctrl[:] = rng.uniform(-1.0, 1.0, 8)
        for _ in range(SUBSTEPS):
            mujoco.mj_step(m, d)
        z = d.qpos[2]
        if not HEALTHY[0] <= z <= HEALTHY[1]:
            ended = "above 1 m" if z > HEALTHY[1] else "torso on the floor"
            break
    _, x, y, _ = d.qpos[3:7]
    print(f"{seed:4d}  {t:5d}  {z:7.3f}  {1 - 2 * (x * x + y * y):5.2f}  {ended}")
