"""MuJoCo C: the reference engine, float64 on the host's cores. The same robot, terrain, controller and summary
as the MJX rollout, with the physics stepped by MuJoCo C on the host's cores (`mujoco.rollout`, one thread pool).

How it differs from the MJX engine, and why:
- Terrain. MJX checks a fixed list of geom pairs, so hexjax moves a few slot boxes under each foot every
  control step. MuJoCo C has a broadphase, so here every terrain box is a geom of its own (`terrain_<j>`,
  `build_mjcf(..., terrain_boxes=M)`) and each env gets its own `MjModel` with its boxes in place. The contact
  parameters are the slot pairs' (condim 3, same friction, default solref / solimp).
- Sensors. Observations come from MuJoCo contact sensors declared in the model
  (`hexjax.sim.model.obs_from_sensordata`): net foot force in the world frame, summed normal force per foot and
  per pad, as `read_obs` computes from MJX's solver rows.
- The controller runs as JAX on the host between control steps, vmapped over the envs of a chunk; the physics
  of one control step (dt / timestep substeps) is one `Rollout.rollout` call over the chunk.
- The start heading, the controller phase (settle posture, perturbed sensing and action) and the summary are the
  MJX control step's own functions (`hexjax.sim.step`: `start_yaw`, `controller_phase`, `accumulate`,
  `summarise`), in float32 (MuJoCo C's state is float64).
- Forward only (no gradients), on the host alone (no device mesh, no range sensors: those are cast in the MJX
  control step). With `RolloutConfig.record` every per-step trace the MJX engine keeps is kept as well: the
  torso's pose, the feet (MuJoCo's foot-site position sensors), the controller's trace, the joints, the foot
  forces and tactile pads the controller read. At the very first control step the sensors read zero (no step has
  run yet); with the default settle time that step is a settling step, whose action is fixed.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from typing import Optional

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

from hexjax.sim import perturb
from hexjax.sim import step as sim_step  # the phase and summarise on the module: tests/test_step.py watches them
from hexjax.sim.config import PhysicsConfig, RolloutConfig, SensorConfig
from hexjax.sim.engines.base import TRACES, Engine, host_cores
from hexjax.sim.mjcf import PARKED_Z, build_mjcf, compile_mjcf, sensor_layout
from hexjax.sim.model import actuator_forces, foot_positions, obs_from_sensordata
from hexjax.sim.perturb import MIN_FRICTION
from hexjax.sim.slip import slip
from hexjax.sim.step import accumulate, init_acc, settle_steps, start_yaw, substeps
from hexjax.world.robot import RobotSpec, quat_yaw

_FULL = mujoco.mjtState.mjSTATE_FULLPHYSICS
PARKED_SPACING = 0.05  # m between parked boxes (0.01 m half sizes): no two overlap


@dataclasses.dataclass
class _Template:
    model: mujoco.MjModel
    box_geoms: np.ndarray
    box_bodies: np.ndarray
    box_bvh: np.ndarray
    ground_geom: int
    torso_body: int
    qpos0: np.ndarray
    ctrl0: np.ndarray
    nstate: int
    pool: list  # MjModel copies reused across calls (filling one costs a few us, copying one ~0.3 ms)


@functools.lru_cache(maxsize=4)
def _template(robot: RobotSpec, physics: PhysicsConfig, n_boxes: int) -> _Template:
    phys = dataclasses.replace(physics, slots_per_leg=0, torso_slots=0)
    # the ground plane moves with each env's ground_z (`_models` writes its geom_pos): see `compile_mjcf`
    m = compile_mjcf(build_mjcf(robot, phys, contact_sensors=True, terrain_boxes=n_boxes))
    gid = lambda n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n)
    key = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "stance")
    assert m.nsensordata == sensor_layout()["size"]
    bodies = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"terrain_{j}") for j in range(n_boxes)], dtype=int)
    return _Template(model=m, box_geoms=np.array([gid(f"terrain_{j}") for j in range(n_boxes)], dtype=int),
                     box_bodies=bodies, box_bvh=np.asarray(m.body_bvhadr[bodies], dtype=int),
                     ground_geom=gid("ground"),
                     torso_body=mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "torso"),
                     qpos0=np.array(m.key_qpos[key]), ctrl0=np.array(m.key_ctrl[key]),
                     nstate=mujoco.mj_stateSize(m, _FULL), pool=[])


def _models(tp: _Template, box_pos, box_half, box_valid, ground_z, pert=None):
    """One MjModel per env (from the reused pool) with that env's terrain boxes and ground height, and with
    `pert` (a host copy of the chunk's `Perturbation`) its draw's model fields (`_perturb_model`)."""
    n = box_pos.shape[0]
    while len(tp.pool) < n:
        tp.pool.append(mujoco.MjModel.__copy__(tp.model))
    # an env with fewer boxes than the batch's fullest parks the rest below the ground, each apart from the others:
    # stacked in one place, every parked pair overlapped in the broadphase and was sorted and filtered every step
    parked = np.stack([PARKED_SPACING * np.arange(box_pos.shape[1]), np.zeros(box_pos.shape[1]),
                       np.full(box_pos.shape[1], PARKED_Z)], -1)
    pos = np.where(box_valid[..., None], box_pos, parked)
    half = np.where(box_valid[..., None], box_half, 0.01)
    out = tp.pool[:n]
    for i, mi in enumerate(out):
        mi.body_pos[tp.box_bodies] = pos[i]
        mi.geom_size[tp.box_geoms] = half[i]
        # collision culling reads the bounding sphere, the geom's box and its body's bounding-volume node,
        # which the compiler made for the placeholder size
        mi.geom_rbound[tp.box_geoms] = np.linalg.norm(half[i], axis=-1)
        mi.geom_aabb[tp.box_geoms, 3:] = half[i]
        mi.bvh_aabb[tp.box_bvh, 3:] = half[i]
        mi.geom_pos[tp.ground_geom, 2] = ground_z[i]
        _perturb_model(tp, mi, None if pert is None else jax.tree_util.tree_map(lambda x: x[i], pert))
    return out


def _perturb_model(tp: _Template, mi: mujoco.MjModel, p) -> None:
    """MjModel `mi` (a pooled copy: every field is written from the template, so a reused copy keeps nothing of
    its last env) with the draw `p` of one env, as `hexjax.sim.perturb.model` does to an mjx.Model: the robot's
    ground contacts are declared pairs (their friction set), its terrain-box contacts take the larger of their
    two geoms' friction (every geom's set). A limp leg's gains are zeroed later, at its onset (`rollout_c`)."""
    m0, b = tp.model, tp.torso_body
    if p is None:
        for f in ("geom_friction", "pair_friction", "body_mass", "body_ipos", "body_inertia", "actuator_gainprm",
                  "actuator_biasprm", "actuator_forcerange", "dof_damping"):
            getattr(mi, f)[:] = getattr(m0, f)
        return
    f = float(p.friction)
    mi.geom_friction[:] = m0.geom_friction
    mi.pair_friction[:] = m0.pair_friction
    if f >= 0:
        mi.geom_friction[:, 0] = max(f, MIN_FRICTION)
        mi.pair_friction[:, :2] = max(f, MIN_FRICTION)
    p64 = p.replace(torso_mass_scale=float(p.torso_mass_scale), payload_kg=float(p.payload_kg),
                    payload_offset=np.asarray(p.payload_offset, np.float64))
    mi.body_mass[:] = m0.body_mass
    mi.body_ipos[:] = m0.body_ipos
    mi.body_inertia[:] = m0.body_inertia
    mi.body_mass[b], mi.body_ipos[b], mi.body_inertia[b] = perturb.torso_with_payload(
        m0.body_mass[b], m0.body_ipos[b], m0.body_inertia[b], p64, xp=np)
    _gains(tp, mi, float(p.kp_scale) * np.ones(m0.nu))
    mi.actuator_forcerange[:] = m0.actuator_forcerange * float(p.torque_scale)
    mi.dof_damping[:] = m0.dof_damping
    mi.dof_damping[6:] *= float(p.damping_scale)


def _gains(tp: _Template, mi: mujoco.MjModel, scale) -> None:
    """Servo gains kp and kv of `mi` set to the template's times `scale` (nu,)."""
    mi.actuator_gainprm[:] = tp.model.actuator_gainprm
    mi.actuator_biasprm[:] = tp.model.actuator_biasprm
    mi.actuator_gainprm[:, 0] *= scale
    mi.actuator_biasprm[:, 1:3] *= scale[:, None]


def rollout_c(robot: RobotSpec, terrain, controller, params, n_ctrl: int, keys, *, physics: PhysicsConfig,
              sensors: SensorConfig, config: RolloutConfig, params_batched: bool = False,
              nthread: Optional[int] = None, chunk: int = 8192, progress: bool = False, perturbation=None):
    """`hexjax.sim.rollout.rollout` on MuJoCo C (checked there): (the same `Summary`; seconds spent compiling
    the controller step). nthread: MuJoCo threads (default: the cores this process may use, `host_cores`);
    chunk: envs per pass (bounds memory; the controller is compiled once for this size). perturbation: a batched
    `Perturbation`, applied as on the MJX path: its model fields in each env's MjModel, its sensing and action
    effects by `hexjax.sim.perturb` in the controller step. With `config.record` the torso trace (x, y, z, yaw per
    control step of the walk) is kept with every other trace of `Summary` (`_traces`)."""
    nthread = int(nthread or host_cores())
    if nthread < 1:
        raise ValueError(f"nthread={nthread!r}: must be >= 1")
    box_pos, box_half = np.asarray(terrain.box_pos, np.float64), np.asarray(terrain.box_half, np.float64)
    box_valid, ground_z = np.asarray(terrain.box_valid, bool), np.asarray(terrain.ground_z, np.float64)
    b = box_pos.shape[0]
    # MuJoCo's broadphase sorts every body at every step, parked or not: keep only as many box bodies as the
    # fullest terrain of the batch has boxes, each env's valid boxes first (148 slots -> ~70 on high-large)
    order = np.argsort(~box_valid, axis=1, kind="stable")
    n_boxes = max(1, int(box_valid.sum(1).max()))
    box_pos, box_half, box_valid = (np.take_along_axis(x, order[..., None] if x.ndim == 3 else order, 1)[:, :n_boxes]
                                    for x in (box_pos, box_half, box_valid))
    tp = _template(robot, physics, n_boxes)
    m0 = tp.model
    nq, nv, nu = m0.nq, m0.nv, m0.nu
    n_sub = substeps(physics, controller.dt)
    n_settle = settle_steps(config, controller.dt)
    dt = physics.timestep
    chunk = max(1, min(int(chunk), b))
    n_chunks = math.ceil(b / chunk)

    yaw0, k_ctrl = jax.vmap(lambda k: start_yaw(config, k))(keys)
    yaw0 = np.asarray(yaw0)
    step_fn, init_fn, ctrl0_fn = _controller_fns(controller, sensors, 0 if params_batched else None,
                                                 perturbation is not None, n_settle)
    pert_all = None if perturbation is None else jax.device_get(perturbation)
    acc_fn = _accumulator(config, controller.dt, n_settle, robot)

    outs = []
    compile_s = 0.0
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=n_chunks * (n_settle + n_ctrl), desc="mujoco-c", unit="ctrl step")
    with mj_rollout.Rollout(nthread=nthread) as pool:
        datas = [mujoco.MjData(m0) for _ in range(nthread)]
        for c in range(n_chunks):
            idx = np.arange(c * chunk, (c + 1) * chunk) % b  # the last chunk wraps round; its extras are dropped
            take = lambda x: jax.tree_util.tree_map(lambda a: a[idx], x)
            prm = take(params) if params_batched else params
            pert = None if pert_all is None else jax.tree_util.tree_map(lambda a: np.asarray(a)[idx], pert_all)
            models = _models(tp, box_pos[idx], box_half[idx], box_valid[idx], ground_z[idx], pert)
            cstate = init_fn(prm, k_ctrl[idx])
            ctrl0 = ctrl0_fn(prm)
            ctrl0 = np.broadcast_to(tp.ctrl0 if ctrl0 is None else np.asarray(ctrl0), (chunk, nu)).astype(np.float32)
            pstate = None if pert is None else jax.vmap(perturb.init_state)(jnp.asarray(ctrl0))
            limp = None if pert is None else np.nonzero(np.asarray(pert.fault_kind) == perturb.LIMP)[0]
            # initial state: neutral stance at (0, 0, yaw0), joints at the settle posture
            qpos = np.broadcast_to(tp.qpos0, (chunk, nq)).copy()
            yw = yaw0[idx]
            qpos[:, 3], qpos[:, 6] = np.cos(yw / 2), np.sin(yw / 2)
            qpos[:, 7:] = ctrl0
            state = np.zeros((chunk, tp.nstate))
            state[:, 1:1 + nq] = qpos
            sens = np.zeros((chunk, m0.nsensordata))
            st_out = np.empty((chunk, n_sub, tp.nstate))
            sd_out = np.empty((chunk, n_sub, m0.nsensordata))
            recs = []
            acc = jax.vmap(init_acc)(jnp.stack([jnp.zeros(chunk), jnp.zeros(chunk), jnp.asarray(yw, jnp.float32)], -1))
            gz = jnp.asarray(ground_z[idx], jnp.float32)
            if c == 0:  # compile the controller step (timed apart, as the MJX rollout's compile is)
                t0 = time.perf_counter()
                jax.block_until_ready(step_fn(prm, cstate, qpos, state[:, 1 + nq:1 + nq + nv], sens, state[:, 0],
                                              np.int32(0), ctrl0, pert, pstate))
                compile_s = time.perf_counter() - t0
            for i in range(n_settle + n_ctrl):
                q, v = state[:, 1:1 + nq], state[:, 1 + nq:1 + nq + nv]
                if pert is not None:
                    # as the MJX step: a limp leg's gains are zero from its onset (the model for this step)
                    t_walk = (i - n_settle) * controller.dt
                    for e in limp:
                        if float(pert.fault_time[e]) <= t_walk < float(pert.fault_time[e]) + controller.dt:
                            _gains(tp, models[e], np.where(np.arange(nu) // 3 == int(pert.fault_leg[e]), 0.0,
                                                           float(pert.kp_scale[e])))
                cstate, action, pstate, obs, trace = step_fn(prm, cstate, q, v, sens, state[:, 0], np.int32(i), ctrl0,
                                                             pert, pstate)
                tactile, contact = obs.tactile, obs.foot_contact
                action = np.asarray(action, np.float64)
                control = np.repeat(action[:, None, :], n_sub, axis=1)
                pool.rollout(models, datas, state, control, control_spec=mujoco.mjtState.mjSTATE_CTRL,
                             nstep=n_sub, state=st_out, sensordata=sd_out, skip_checks=True)
                new_state = st_out[:, -1]
                finite = np.all(np.isfinite(new_state), axis=1)
                power = np.abs(actuator_forces(sd_out) * st_out[..., 1 + nq + 6:1 + nq + nv]).sum((1, 2))
                new_state = np.where(finite[:, None], new_state, state)
                acc = acc_fn(acc, i, q.astype(np.float32), new_state[:, 1:1 + nq].astype(np.float32), finite,
                             (power * dt).astype(np.float32), tactile, gz, contact)
                state = new_state
                if config.record and i >= n_settle:
                    recs.append((new_state[:, 1:1 + nq].astype(np.float32),
                                 foot_positions(sd_out[:, -1]).astype(np.float32), trace, obs.foot_force, tactile))
                sens = np.where(finite[:, None], sd_out[:, -1], sens)
                if config.progress_every and (i + 1) % config.progress_every == 0:  # as the MJX scan reports
                    sim_step._report_progress(i + 1)
                if progress:
                    bar.update(1)
            outs.append((acc, cstate, state[:, 1:1 + nq].astype(np.float32), _traces(recs) if config.record else {}))
    if progress:
        bar.close()
    cat = lambda *xs: jnp.concatenate(xs)[:b]
    acc = jax.tree_util.tree_map(cat, *[o[0] for o in outs])
    final = jax.tree_util.tree_map(cat, *[o[1] for o in outs])
    q_end = cat(*[o[2] for o in outs])
    traces = jax.tree_util.tree_map(cat, *[o[3] for o in outs]) if config.record else {}
    return sim_step.summarise(acc, q_end, final, **traces), compile_s


def _traces(recs):
    """`Summary`'s per-step traces of a chunk (each (n, T, ...)) from its walking steps' records (joint positions
    after the step, feet after it, the controller's trace, the foot forces and tactile pads it read)."""
    qpos, feet, ctrl, force, tactile = (jax.tree_util.tree_map(lambda *x: jnp.stack(x, 1), *col) for col in zip(*recs))
    pose = jnp.concatenate([qpos[..., :3], quat_yaw(qpos[..., 3:7])[..., None]], -1)
    return dict(trace=pose, foot_trace=feet, ctrl_trace=ctrl, qpos_trace=qpos, force_trace=force,
                tactile_trace=tactile)


@dataclasses.dataclass(frozen=True)
class MuJoCoC(Engine):
    """MuJoCo C through `mujoco.rollout` on a thread pool; the controller between control steps in JAX."""

    def rollout(self, robot, terrain, controller, params, n_ctrl, keys, *, physics, sensors, config,
                params_batched, mesh, nthread, perturbation):
        out, compile_s = rollout_c(robot, terrain, controller, params, n_ctrl, keys, physics=physics,
                                   sensors=sensors, config=config, params_batched=params_batched, nthread=nthread,
                                   perturbation=perturbation)
        return out, compile_s, "compiled" if compile_s else "process"


# bytes_per_env: each env's MjModel copy (141,715 bytes with `high-large`'s 97 boxes) and its float64 state,
# sensors and per-step outputs (about 20 kB)
C_ENGINE = MuJoCoC(name="c", title="MuJoCo C", precision="float64", can=frozenset({TRACES}), hosts=("cpu",),
                   culls=False, bytes_per_env=162_000)


@functools.lru_cache(maxsize=16)
def _controller_fns(controller, sensors: SensorConfig, p_axis, perturbed: bool = False, n_settle: int = 0):
    """Jitted, vmapped controller step of one chunk (from MuJoCo's sensordata through the MJX control step's
    `controller_phase`: the settle posture while settling and, with `perturbed`, the draws' sensing and action
    effects), its init and its settle posture. The step returns (controller state, targets, perturbation state,
    the true `Obs`, the controller's trace of the step)."""
    def step(params, cstate, qpos, qvel, sens, t, i, ctrl0, pert, pstate):
        obs = obs_from_sensordata(sensors, qpos.astype(jnp.float32), qvel.astype(jnp.float32),
                                  sens.astype(jnp.float32), t.astype(jnp.float32))
        cstate, action, pstate, seen = sim_step.controller_phase(controller, sensors, params, cstate, obs, i,
                                                                 n_settle, ctrl0, pert, pstate)
        return cstate, action, pstate, obs, controller.trace(cstate, seen)

    e = 0 if perturbed else None  # the draws and their state: per env, or None
    step_b = jax.jit(jax.vmap(step, in_axes=(p_axis, 0, 0, 0, 0, 0, None, 0, e, e)))
    init_b = jax.jit(jax.vmap(controller.init, in_axes=(p_axis, 0)))
    # (n, nu) for batched params, (nu,) for shared ones (broadcast by the caller), or None: the stance
    ctrl0_b = jax.jit(jax.vmap(controller.initial_action) if p_axis == 0 else controller.initial_action)
    return step_b, init_b, ctrl0_b


@functools.lru_cache(maxsize=16)
def _accumulator(config: RolloutConfig, ctrl_dt: float, n_settle: int, robot: RobotSpec):
    """`hexjax.sim.step.accumulate` over a chunk of envs (the MJX rollout's own summary arithmetic), foot slip
    included (`hexjax.sim.slip`, from the feet in contact at the step's start)."""
    def one(acc, i, q_old, q_new, finite, energy, tactile, ground_z, contact):
        return accumulate(acc, config, i, n_settle, ctrl_dt, q_old, q_new, finite, energy, tactile, ground_z,
                          slip(robot, q_old, q_new, contact))

    return jax.jit(jax.vmap(one, in_axes=(0, None, 0, 0, 0, 0, 0, 0, 0)))
