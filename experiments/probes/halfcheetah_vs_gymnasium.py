"""Our half-cheetah against Gymnasium's HalfCheetah-v5: the compiled models, one trajectory in
lockstep, and random-action returns.

An independent check that sim-bridge's half-cheetah (sim-bridge/assets/halfcheetah.xml with the
task's reward, mirrored here) is the environment the paper used (gym's HalfCheetah, as PETS ran
it: 0.01 s Euler steps, five per 0.05 s control step, reward `Δx/dt − 0.1 ‖a‖²`):

1. **The compiled models**, field by field (masses, inertias, body and joint frames, joint
   ranges, springs, dampers, armature, gears, control ranges, friction, contact and joint-limit
   softness, geom sizes and positions, timestep, integrator): the largest difference of each.
   Inertias are compared as tensors in the body frame and capsules by their end points (a
   capsule has no front or back).
2. **Lockstep**: both models from the same perturbed state under the same random actions; the
   largest difference of qpos and qvel after 1, 10 and 50 control steps, beside the same for
   HalfCheetah-v5 against itself started 1e-8 m apart (how fast a tiny difference grows in
   this system of contacts on its own).
3. **Random actions**: `--episodes` episodes of 1,000 steps of uniform random actions in
   [−1, 1]⁶ from each model's own reset (ours: N(0, 0.001) on qpos and qvel, tasks.md;
   HalfCheetah-v5's: its defaults), with the return, the distance run and the share of steps
   the cheetah spends upside down (torso pitched beyond 90°, cos(pitch) < 0: on its back), and
   the difference of the means of the return and of that share, each with a 95 % bootstrap
   interval. A planner learns from these episodes first, so how often random actions flip
   the cheetah decides how familiar lying on its back is to the models and the energy.

Needs the project's Python environment (`make python-env`: gymnasium[mujoco]):

    .venv/bin/python experiments/probes/halfcheetah_vs_gymnasium.py [--episodes 100] [--model XML]
"""

import argparse
import pathlib

import gymnasium as gym
import mujoco
import numpy as np

MODEL = pathlib.Path(__file__).resolve().parents[2] / "sim-bridge" / "assets" / "halfcheetah.xml"
SUBSTEPS, EPISODE, RESET_STD, DT = 5, 1000, 0.001, 0.05

FIELDS = [
    "body_mass", "body_inertia", "body_pos", "body_ipos", "jnt_range", "jnt_axis", "jnt_pos",
    "jnt_stiffness", "dof_damping", "dof_armature", "actuator_gear", "actuator_ctrlrange",
    "geom_friction", "geom_solref", "geom_solimp", "jnt_solref", "jnt_solimp", "geom_margin",
    "geom_condim", "geom_contype", "geom_conaffinity", "qpos0",
]


def inertia_tensor(m, b):
    """Body `b`'s inertia tensor about its centre of mass, in the body's frame."""
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, m.body_iquat[b])
    r = rot.reshape(3, 3)
    return r @ np.diag(m.body_inertia[b]) @ r.T


def capsule_ends(m, g):
    """The end points of capsule `g` in its body's frame (a set: either order)."""
    rot = np.zeros(9)
    mujoco.mju_quat2Mat(rot, m.geom_quat[g])
    axis = rot.reshape(3, 3)[:, 2] * m.geom_size[g, 1]
    ends = sorted([tuple(m.geom_pos[g] - axis), tuple(m.geom_pos[g] + axis)])
    return np.array(ends)


def compare_models(ours, theirs):
    print("compiled models, largest |ours − HalfCheetah-v5| per field:")
    for f in FIELDS:
        d = float(np.abs(np.asarray(getattr(ours, f), float) - getattr(theirs, f)).max())
        print(f"  {f:<20} {d:.1e}")
    # Inertia tensors in the body frames (a rod's two equal moments leave its principal
    # frame free to turn about the rod, so the frames themselves need not agree).
    tensors = max(
        float(np.abs(inertia_tensor(ours, b) - inertia_tensor(theirs, b)).max())
        for b in range(1, ours.nbody)
    )
    print(f"  {'inertia tensors':<20} {tensors:.1e} kg m²")
    limbs = [g for g in range(ours.ngeom) if ours.geom_type[g] == mujoco.mjtGeom.mjGEOM_CAPSULE]
    ends = max(
        float(np.abs(capsule_ends(ours, g) - capsule_ends(theirs, g)).max()) for g in limbs
    )
    radii = float(np.abs(ours.geom_size[limbs, 0] - theirs.geom_size[limbs, 0]).max())
    print(f"  {'capsule ends':<20} {ends:.1e} m, radii {radii:.1e} m")
    print(
        f"  total mass {ours.body_mass.sum():.4f} against {theirs.body_mass.sum():.4f} kg; "
        f"timestep {ours.opt.timestep} / {theirs.opt.timestep}, integrator "
        f"{ours.opt.integrator} / {theirs.opt.integrator}"
    )


def lockstep(ours, theirs, label, seed=0, nudge=0.0):
    """Both models from one perturbed state (the second's qpos moved by `nudge`) under the
    same actions: the state difference."""
    rng = np.random.default_rng(seed)
    d1, d2 = mujoco.MjData(ours), mujoco.MjData(theirs)
    q, v = rng.normal(0, 0.1, ours.nq), rng.normal(0, 0.1, ours.nv)
    for m, d, dq in ((ours, d1, 0.0), (theirs, d2, nudge)):
        d.qpos[:], d.qvel[:] = q + dq, v
        mujoco.mj_forward(m, d)
    out = {}
    for step in range(1, 51):
        a = rng.uniform(-1, 1, 6)
        for m, d in ((ours, d1), (theirs, d2)):
            d.ctrl[:] = a
            for _ in range(SUBSTEPS):
                mujoco.mj_step(m, d)
        if step in (1, 10, 50):
            out[step] = (
                float(np.abs(d1.qpos - d2.qpos).max()),
                float(np.abs(d1.qvel - d2.qvel).max()),
            )
    for step, (dq, dv) in out.items():
        print(f"  {label} after {step:>2} steps: max |Δqpos| {dq:.1e}, max |Δqvel| {dv:.1e}")
    return out


def ours_episode(m, seed):
    """One random-action episode of sim-bridge's half-cheetah task (its Rust code, mirrored)."""
    d = mujoco.MjData(m)
    rng = np.random.default_rng(seed)
    d.qpos[:] = m.qpos0 + rng.normal(0, RESET_STD, m.nq)
    d.qvel[:] = rng.normal(0, RESET_STD, m.nv)
    mujoco.mj_forward(m, d)
    x0, ret, upside_down = d.qpos[0], 0.0, 0
    for _ in range(EPISODE):
        a = rng.uniform(-1, 1, 6)
        before = d.qpos[0]
        d.ctrl[:] = a
        for _ in range(SUBSTEPS):
            mujoco.mj_step(m, d)
        ret += (d.qpos[0] - before) / DT - 0.1 * float(a @ a)
        upside_down += np.cos(d.qpos[2]) < 0
    return ret, d.qpos[0] - x0, upside_down / EPISODE


def gymnasium_episode(seed):
    env = gym.make("HalfCheetah-v5", max_episode_steps=EPISODE)
    env.reset(seed=seed)
    rng = np.random.default_rng(10_000 + seed)
    x0, ret, upside_down, steps = env.unwrapped.data.qpos[0], 0.0, 0, 0
    for _ in range(EPISODE):
        _, r, _, truncated, _ = env.step(rng.uniform(-1, 1, 6))
        ret += r
        steps += 1
        upside_down += np.cos(env.unwrapped.data.qpos[2]) < 0
        if truncated:
            break
    dist = env.unwrapped.data.qpos[0] - x0
    env.close()
    return ret, dist, upside_down / steps


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--model", type=pathlib.Path, default=MODEL, help="another MJCF")
    args = parser.parse_args()
    print(f"mujoco {mujoco.__version__}, gymnasium {gym.__version__}, model {args.model.name}")
    ours = mujoco.MjModel.from_xml_path(str(args.model))
    theirs = gym.make("HalfCheetah-v5").unwrapped.model
    compare_models(ours, theirs)
    lockstep(ours, theirs, "ours and v5 in lockstep")
    # How fast 1e-8 m grows on its own in this system (contacts make it chaotic).
    lockstep(theirs, theirs, "v5 and v5 nudged 1e-8 m", nudge=1e-8)
    mine = np.array([ours_episode(ours, s) for s in range(args.episodes)])
    gyms = np.array([gymnasium_episode(s) for s in range(args.episodes)])
    for name, runs in (("ours", mine), ("HalfCheetah-v5", gyms)):
        print(
            f"  {name:<15} random actions, {len(runs)} episodes: return "
            f"{runs[:, 0].mean():.1f} ± {runs[:, 0].std(ddof=1):.1f}, distance "
            f"{runs[:, 1].mean():.2f} ± {runs[:, 1].std(ddof=1):.2f} m, upside down "
            f"{100 * runs[:, 2].mean():.1f} ± {100 * runs[:, 2].std(ddof=1):.1f} % of steps "
            f"(in {np.count_nonzero(runs[:, 2] > 0)} episodes)"
        )
    rng = np.random.default_rng(0)
    for column, what, scale in ((0, "return", 1), (2, "upside-down share (%)", 100)):
        ours_col, theirs_col = scale * mine[:, column], scale * gyms[:, column]
        diffs = [
            rng.choice(ours_col, len(ours_col)).mean()
            - rng.choice(theirs_col, len(theirs_col)).mean()
            for _ in range(10_000)
        ]
        lo, hi = np.percentile(diffs, [2.5, 97.5])
        print(
            f"  {what}: ours − HalfCheetah-v5 = {ours_col.mean() - theirs_col.mean():.1f}, "
            f"95 % interval [{lo:.1f}, {hi:.1f}]"
        )


if __name__ == "__main__":
    main()
