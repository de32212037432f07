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
from concurrent.futures import ThreadPoolExecutor
from typing import Optional

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from mujoco import rollout as mj_rollout

from hexjax.sim import perturb
from hexjax.sim import step as sim_step  # the phase and summarise on the module: tests/test_step.py watches them
from hexjax.sim.config import PhysicsConfig, RolloutConfig, SensorConfig, settle_steps, substeps
from hexjax.sim.engines.base import TRACES, Engine, host_cores
from hexjax.sim.engines.c_models import _gains, _models, _template
from hexjax.sim.memory import check_fits
from hexjax.sim.model import actuator_forces, foot_positions, obs_from_sensordata
from hexjax.sim.slip import slip
from hexjax.sim.step import accumulate, init_acc, start_yaw
from hexjax.world.robot import RobotSpec, quat_yaw


class _Lane:
    """A share of a chunk's envs stepped as one: its models, MuJoCo state and sensors, controller and perturbation
    state, summary accumulator, records, and the buffers the physics writes while the other lane's controller
    runs. `control(i)` runs the controller for control step i and fills the physics' inputs; `finish(i)` reads
    what the physics made of them."""

    def __init__(self, run, idx, models, datas):
        self.r, self.idx, self.models, self.datas = run, idx, models, datas
        r, n = run, len(idx)
        nq = r.m0.nq
        take = lambda x: jax.tree_util.tree_map(lambda a: np.asarray(a)[idx], x)
        self.prm = jax.tree_util.tree_map(lambda a: a[idx], r.params) if r.params_batched else r.params
        self.pert = None if r.pert is None else take(r.pert)
        self.cstate = r.init_fn(self.prm, r.k_ctrl[idx])
        ctrl0 = r.ctrl0_fn(self.prm)
        ctrl0 = r.tp.ctrl0 if ctrl0 is None else np.asarray(ctrl0)
        self.ctrl0 = np.broadcast_to(ctrl0, (n, r.m0.nu)).astype(np.float32)
        self.pstate = None if self.pert is None else jax.vmap(perturb.init_state)(jnp.asarray(self.ctrl0))
        self.limp = None if self.pert is None else np.nonzero(np.asarray(self.pert.fault_kind) == perturb.LIMP)[0]
        # initial state: neutral stance at (0, 0, yaw0), joints at the settle posture
        qpos = np.broadcast_to(r.tp.qpos0, (n, nq)).copy()
        yw = r.yaw0[idx]
        qpos[:, 3], qpos[:, 6] = np.cos(yw / 2), np.sin(yw / 2)
        qpos[:, 7:] = self.ctrl0
        self.state = np.zeros((n, r.tp.nstate))
        self.state[:, 1:1 + nq] = qpos
        self.sens = np.zeros((n, r.m0.nsensordata))
        self.control_in = np.empty((n, r.n_sub, r.m0.nu))
        self.st_out = np.empty((n, r.n_sub, r.tp.nstate))
        self.sd_out = np.empty((n, r.n_sub, r.m0.nsensordata))
        self.recs = []
        self.acc = jax.vmap(init_acc)(jnp.stack([jnp.zeros(n), jnp.zeros(n), jnp.asarray(yw, jnp.float32)], -1))
        self.gz = jnp.asarray(r.ground_z[idx], jnp.float32)

    def step_args(self, i):
        nq, nv = self.r.m0.nq, self.r.m0.nv
        return (self.prm, self.cstate, self.state[:, 1:1 + nq], self.state[:, 1 + nq:1 + nq + nv], self.sens,
                self.state[:, 0], np.int32(i), self.ctrl0, self.pert, self.pstate)

    def control(self, i):
        r, pert = self.r, self.pert
        if pert is not None:
            # as the MJX step: a limp leg's gains are zero from its onset (the model for this step)
            t_walk = (i - r.n_settle) * r.ctrl_dt
            for e in self.limp:
                if float(pert.fault_time[e]) <= t_walk < float(pert.fault_time[e]) + r.ctrl_dt:
                    _gains(r.tp, self.models[e], np.where(np.arange(r.m0.nu) // 3 == int(pert.fault_leg[e]), 0.0,
                                                          float(pert.kp_scale[e])))
        self.q = self.state[:, 1:1 + r.m0.nq].copy()
        self.cstate, action, self.pstate, self.obs, self.trace = r.step_fn(*self.step_args(i))
        self.control_in[:] = np.asarray(action, np.float64)[:, None, :]

    def physics(self, pool):
        pool.rollout(self.models, self.datas, self.state, self.control_in, control_spec=mujoco.mjtState.mjSTATE_CTRL,
                     nstep=self.r.n_sub, state=self.st_out, sensordata=self.sd_out, skip_checks=True)

    def finish(self, i):
        r, nq, nv = self.r, self.r.m0.nq, self.r.m0.nv
        new_state = self.st_out[:, -1]
        finite = np.all(np.isfinite(new_state), axis=1)
        power = np.abs(actuator_forces(self.sd_out) * self.st_out[..., 1 + nq + 6:1 + nq + nv]).sum((1, 2))
        self.state = np.where(finite[:, None], new_state, self.state)
        obs = self.obs
        self.acc = r.acc_fn(self.acc, i, self.q.astype(np.float32), self.state[:, 1:1 + nq].astype(np.float32),
                            finite, (power * r.dt).astype(np.float32), obs.tactile, self.gz, obs.foot_contact)
        if r.config.record and i >= r.n_settle:
            self.recs.append((self.state[:, 1:1 + nq].astype(np.float32),
                              foot_positions(self.sd_out[:, -1]).astype(np.float32), self.trace, obs.foot_force,
                              obs.tactile))
        self.sens = np.where(finite[:, None], self.sd_out[:, -1], self.sens)


def rollout_c(robot: RobotSpec, terrain, controller, params, n_ctrl: int, keys, *, physics: PhysicsConfig,
              sensors: SensorConfig, config: RolloutConfig, params_batched: bool = False,
              nthread: Optional[int] = None, chunk: int = 8192, lanes: Optional[int] = None, progress: bool = False,
              perturbation=None):
    """`hexjax.sim.rollout.rollout` on MuJoCo C (checked there): (the same `Summary`; seconds spent compiling
    the controller step). nthread: MuJoCo threads (default: the cores this process may use, `host_cores`);
    chunk: envs per pass (bounds memory; the controller is compiled once for a lane of it); lanes: how many
    lanes a chunk steps as (below; 1: the controller and physics one after the other; default 1 under 128 envs a
    chunk, 2 under 1,024, else 4: as many as keep a lane's physics longer than the others' controllers and
    split a chunk of mixed terrains by box count). perturbation: a batched
    `Perturbation`, applied as on the MJX path: its model fields in each env's MjModel, its sensing and action
    effects by `hexjax.sim.perturb` in the controller step. With `config.record` the torso trace (x, y, z, yaw
    per control step of the walk) is kept with every other trace of `Summary` (`_traces`).

    A chunk's envs step as lanes: while MuJoCo's threads step one lane's physics, this thread runs the other
    lanes' controllers and summaries (JAX) and reads their physics' outputs, which would otherwise leave the
    threads idle between control steps (half the time on 16 cores). The lanes split the chunk by box count (the
    fewer boxes in the first), each lane's models with as many box slots as its own fullest terrain needs."""
    nthread = int(nthread or host_cores())
    if nthread < 1:
        raise ValueError(f"nthread={nthread!r}: must be >= 1")
    box_pos, box_half = np.asarray(terrain.box_pos, np.float64), np.asarray(terrain.box_half, np.float64)
    box_valid = np.asarray(terrain.box_valid, bool)
    b = box_pos.shape[0]
    counts = box_valid.sum(1)
    # each lane's models hold as many box slots as its fullest terrain has boxes, rounded up to a square grid (every
    # geom costs its kinematics at every step; 148 slots hold at most 70 boxes on high-large: 100 geoms)
    template = lambda n: _template(robot, physics, math.ceil(math.sqrt(max(1, int(n)))))
    tp = template(counts.max())
    n_settle = settle_steps(config, controller.dt)
    chunk = max(1, min(int(chunk), b))
    n_lanes = max(1, min(int(lanes if lanes is not None else (1 if chunk < 128 else 2 if chunk < 1024 else 4)), chunk))
    chunk = n_lanes * math.ceil(chunk / n_lanes)
    n_chunks = math.ceil(b / chunk)
    yaw0, k_ctrl = jax.vmap(lambda k: start_yaw(config, k))(keys)
    step_fn, init_fn, ctrl0_fn = _controller_fns(controller, sensors, 0 if params_batched else None,
                                                 perturbation is not None, n_settle)
    run = _Run(tp=tp, m0=tp.model, params=params, params_batched=params_batched, k_ctrl=k_ctrl,
               yaw0=np.asarray(yaw0), ground_z=np.asarray(terrain.ground_z, np.float64),
               pert=None if perturbation is None else jax.device_get(perturbation), init_fn=init_fn,
               ctrl0_fn=ctrl0_fn, step_fn=step_fn, acc_fn=_accumulator(config, controller.dt, n_settle, robot),
               n_sub=substeps(physics, controller.dt), n_settle=n_settle, ctrl_dt=controller.dt,
               dt=physics.timestep, config=config)
    n_steps = n_settle + n_ctrl

    outs = []
    compile_s = 0.0
    if progress:
        from tqdm.auto import tqdm
        bar = tqdm(total=n_chunks * n_steps, desc="mujoco-c", unit="ctrl step")
    with mj_rollout.Rollout(nthread=nthread) as pool, ThreadPoolExecutor(1, "mujoco-c") as worker:
        datas = {}  # MjData for each template's models, one a thread
        for c in range(n_chunks):
            idx = np.arange(c * chunk, (c + 1) * chunk) % b  # the last chunk wraps round; its extras are dropped
            # the lanes split the chunk by box count, so that a lane of few boxes does not carry another's empty slots
            order = np.argsort(counts[idx], kind="stable")
            w = chunk // n_lanes
            running, used = [], {}
            for k in range(n_lanes):
                sel = idx[order[k * w:(k + 1) * w]]
                tk = template(counts[sel].max())
                pert = None if run.pert is None else jax.tree_util.tree_map(lambda a: np.asarray(a)[sel], run.pert)
                models = _models(tk, box_pos[sel], box_half[sel], box_valid[sel], run.ground_z[sel], pert,
                                 start=used.get(tk.k, 0))
                used[tk.k] = used.get(tk.k, 0) + w
                if tk.k not in datas:
                    datas[tk.k] = [mujoco.MjData(tk.model) for _ in range(nthread)]
                running.append(_Lane(run, sel, models, datas[tk.k]))
            if c == 0:  # compile the controller step (timed apart, as the MJX rollout's compile is)
                t0 = time.perf_counter()
                jax.block_until_ready(step_fn(*running[0].step_args(0)))
                compile_s = time.perf_counter() - t0
            busy = [None] * n_lanes
            # one physics call at a time (one thread pool), in lane order: lane k's physics of step i runs while the
            # lanes after it are read and controlled for step i and those before it for step i + 1
            for i in range(n_steps + 1):
                for k, lane in enumerate(running):
                    if busy[k] is not None:
                        busy[k].result()
                        lane.finish(i - 1)
                        if config.record and c == 0 and k == 0 and i - 1 == n_settle:
                            _check_record_memory(lane, b, n_ctrl)
                    if i < n_steps:
                        lane.control(i)
                        busy[k] = worker.submit(lane.physics, pool)
                if i and config.progress_every and i % config.progress_every == 0:  # as the MJX scan reports
                    sim_step._report_progress(i)
                if i and progress:
                    bar.update(1)
            back = np.argsort(order, kind="stable")  # the lanes' envs back in the chunk's order
            cat = lambda *xs: jnp.concatenate(xs)[back]
            nq = tp.model.nq
            outs.append(jax.tree_util.tree_map(cat, *[(ln.acc, ln.cstate, ln.state[:, 1:1 + nq].astype(np.float32),
                                                       _traces(ln.recs) if config.record else {}) for ln in running]))
    if progress:
        bar.close()
    cat = lambda *xs: jnp.concatenate(xs)[:b]
    acc, final, q_end, traces = jax.tree_util.tree_map(cat, *outs)
    return sim_step.summarise(acc, q_end, final, **traces), compile_s


@dataclasses.dataclass(frozen=True)
class _Run:
    """What every lane of one `rollout_c` call shares."""
    tp: object
    m0: mujoco.MjModel
    params: object
    params_batched: bool
    k_ctrl: object
    yaw0: np.ndarray
    ground_z: np.ndarray
    pert: object
    init_fn: object
    ctrl0_fn: object
    step_fn: object
    acc_fn: object
    n_sub: int
    n_settle: int
    ctrl_dt: float
    dt: float
    config: RolloutConfig


# a walk's records are held three times over at its end: the per-step list, its stacked copy, the joined batch
RECORD_COPIES = 3


def _check_record_memory(lane: _Lane, n_envs: int, n_ctrl: int) -> None:
    """One ValueError line seconds into the walk, instead of the host running out of memory at its end: the traces
    `RolloutConfig.record` keeps for `n_envs` envs over `n_ctrl` control steps, measured from one lane's first
    walking step, against the host's memory."""
    step = sum(np.asarray(x).nbytes for x in jax.tree_util.tree_leaves(lane.recs[0]))
    per_env = int(RECORD_COPIES * step / len(lane.idx) * n_ctrl)
    check_fits("envs", n_envs, per_env, f"keeping every trace of a {n_ctrl}-control-step walk on MuJoCo C "
               "(rollout.record)", host=True)


def _traces(recs):
    """`Summary`'s per-step traces of a chunk (each (n, T, ...)) from its walking steps' records (joint positions
    after the step, feet after it, the controller's trace, the foot forces and tactile pads it read)."""
    qpos, feet, ctrl, force, tactile = (jax.tree_util.tree_map(lambda *x: jnp.stack(x, 1), *col) for col in zip(*recs))
    pose = jnp.concatenate([qpos[..., :3], quat_yaw(qpos[..., 3:7])[..., None]], -1)
    return dict(trace=pose, foot_trace=feet, ctrl_trace=ctrl, qpos_trace=qpos, force_trace=force,
                tactile_trace=tactile)


@dataclasses.dataclass(frozen=True)
class MuJoCoC(Engine):
    """MuJoCo C through `mujoco.rollout` on a thread pool; the controller between control steps in JAX on the
    host's CPU (on a GPU host too: a control step's inputs come from, and its targets go to, host memory)."""

    def rollout(self, robot, terrain, controller, params, n_ctrl, keys, *, physics, sensors, config,
                params_batched, mesh, nthread, perturbation):
        with jax.default_device(jax.devices("cpu")[0]):
            out, compile_s = rollout_c(robot, terrain, controller, params, n_ctrl, keys, physics=physics,
                                       sensors=sensors, config=config, params_batched=params_batched,
                                       nthread=nthread, perturbation=perturbation)
        return out, compile_s, "compiled" if compile_s else "process"


# bytes_per_env: each env's MjModel copy (115,177 bytes with `high-large`'s 97 boxes in 100 slots) and its float64
# state, sensors and per-step outputs (about 20 kB)
C_ENGINE = MuJoCoC(name="c", title="MuJoCo C", precision="float64", can=frozenset({TRACES}), hosts=("cpu",),
                   culls=False, bytes_per_env=136_000)


@functools.lru_cache(maxsize=16)
def _controller_fns(controller, sensors: SensorConfig, p_axis, perturbed: bool = False, n_settle: int = 0):
    """Jitted, vmapped controller step of one chunk (from MuJoCo's sensordata through the MJX control step's
    `controller_phase`: the settle posture while settling and, with `perturbed`, the draws' sensing and action
    effects), its init and its settle posture. The step returns (controller state, targets, perturbation state,
    the true `Obs`, the controller's trace of the step)."""
    def step(params, cstate, qpos, qvel, sens, t, i, ctrl0, pert, pstate):
        obs = obs_from_sensordata(sensors, qpos.astype(jnp.float32), qvel.astype(jnp.float32),
                                  sens.astype(jnp.float32), t.astype(jnp.float32))
        clock = sim_step.StepClock(i, n_settle, controller.dt)
        cstate, action, pstate, seen = sim_step.controller_phase(controller, sensors, params, cstate, obs, clock,
                                                                 ctrl0, pert, pstate)
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
        return accumulate(acc, config, sim_step.StepClock(i, n_settle, ctrl_dt), q_old, q_new, finite, energy,
                          tactile, ground_z, slip(robot, q_old, q_new, contact))

    return jax.jit(jax.vmap(one, in_axes=(0, None, 0, 0, 0, 0, 0, 0, 0)))
