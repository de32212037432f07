"""Host-side model building, per-env terrain slots and sensor extraction for the MJX rollout.

Terrain culling. MJX evaluates one collision function per declared geom pair every step, so a terrain of
hundreds of boxes cannot be declared as geoms. Instead each leg owns `slots_per_leg` box geoms (and the
torso `torso_slots`); every control step `assign_slots` moves them onto the terrain boxes nearest that
leg's foot, so the pair count stays 7 + 2 * 6 * slots_per_leg + torso_slots whatever the terrain size.
Only geom_pos / geom_size of the slot geoms differ per env (a batch axis on those two fields only).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from flax import struct

from hexjax.sim.config import PhysicsConfig, SensorConfig
from hexjax.sim.mjcf import PARKED_Z, SENSOR_MATCHES, build_mjcf, sensor_layout
from hexjax.sim.internals.contacts import contact_forces, contact_geoms
from hexjax.sim.internals.rules import mjx  # imported there without MJX's notice about the optional Warp backend
from hexjax.world.robot import LEG_NAMES, N_LEGS, RobotSpec, neutral_feet_body
from hexjax.world.terrain import Terrain

SLOT_REACH = 0.12  # m: terrain boxes farther than this from a foot are not given a slot


@struct.dataclass
class Obs:
    """What a controller sees each control step (one env; add a leading axis when batched).

    qpos (18,) rad, qvel (18,) rad/s      joint angles and rates, leg order LF..RH x (coxa, femur, tibia)
    torso_pos (3,) m, torso_quat (4,)    world frame (w, x, y, z)
    foot_force (6, 3) N                  contact force on each foot from the terrain, world frame
    foot_contact (6,) bool               normal foot force above `SensorConfig.contact_threshold`
    tactile_force (6,) N                 normal force on each shin's front tactile pad
    tactile (6,) bool                    tactile pad on/off (force above `tactile_threshold`)
    time () s                            since the start of the rollout
    """

    qpos: jax.Array
    qvel: jax.Array
    torso_pos: jax.Array
    torso_quat: jax.Array
    foot_force: jax.Array
    foot_contact: jax.Array
    tactile_force: jax.Array
    tactile: jax.Array
    time: jax.Array


class SimModel:
    """MuJoCo / MJX models of one robot with terrain slots, plus static index maps. Built once on the host.

    engine: an MJX-family engine of `hexjax.sim.engines` (`hexjax.sim.engines.sim_model` takes its name): MJX
    in JAX or MuJoCo Warp's kernels through MJX, which puts the model on the device and whose model may declare
    MuJoCo's contact sensors, read by its observations (`obs_from_sensordata`)."""

    def __init__(self, robot: RobotSpec, physics: PhysicsConfig, engine):
        if not hasattr(engine, "put_model"):
            raise ValueError(f"engine={engine.name!r}: SimModel is the MJX family's model (mjx, warp)")
        physics.validate()
        for f in ("slots_per_leg", "torso_slots"):
            if getattr(physics, f) is None:
                raise ValueError(f"physics.{f}=None: give the terrain's count (`PhysicsPreset.config(terrain)`)")
        self.robot, self.physics, self.engine = robot, physics, engine
        self.xml = build_mjcf(robot, physics, contact_sensors=engine.contact_sensors)
        self.mj_model = mujoco.MjModel.from_xml_string(self.xml)
        self.mjx_model = engine.put_model(self.mj_model)
        m = self.mj_model
        gid = lambda n: mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n)
        self.ground_geom = gid("ground")
        self.foot_geoms = np.array([gid(f"{n}_foot") for n in LEG_NAMES])
        self.pad_geoms = np.array([gid(f"{n}_pad") for n in LEG_NAMES])
        k = physics.slots_per_leg
        self.leg_slot_geoms = np.array([[gid(f"slot_{n}_{j}") for j in range(k)] for n in LEG_NAMES],
                                       dtype=int).reshape(N_LEGS, k)
        self.torso_slot_geoms = np.array([gid(f"slot_torso_{j}") for j in range(physics.torso_slots)], dtype=int)
        self.foot_sites = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"{n}_foot") for n in LEG_NAMES])
        self.torso_body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "torso")
        key = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_KEY, "stance")
        self.qpos0 = np.array(m.key_qpos[key])
        self.ctrl0 = np.array(m.key_ctrl[key])
        self.n_pairs = m.npair
        # Static contact -> (foot, pad) membership. MJX lays contacts out by pair group, each group
        # repeated by its collision function's contact count; that order is fixed at trace time, so
        # the map holds for every step of every env (tests/test_sim.py checks it against mjx.forward).
        # Computed on MJX's JAX implementation for every engine (for MuJoCo Warp it gives the per-world contact and
        # row counts). MJX's JAX implementation lacks the netforce contact sensor: the map is built on a model
        # without sensors.
        m_jax = mujoco.MjModel.from_xml_string(build_mjcf(robot, physics)) if engine.contact_sensors else m
        dev = jax.local_devices()[0]
        d = mjx.make_data(m_jax, impl="jax", device=dev)
        geoms = contact_geoms(mjx.put_model(m_jax, impl="jax", device=dev) if engine.contact_sensors
                              else self.mjx_model, d)
        self.ncon = geoms.shape[0]
        self.contact_foot = np.stack([(geoms == g).any(1) for g in self.foot_geoms], 1).astype(np.float32)
        self.contact_pad = np.stack([(geoms == g).any(1) for g in self.pad_geoms], 1).astype(np.float32)
        # MuJoCo's contact force acts on geom2 from geom1. MJX orders each pair by geom type, so the robot
        # geom is geom2 against the ground plane but geom1 against a terrain box (sphere/capsule < box):
        # +1 where the robot geom is geom2, -1 where it is geom1.
        robot = np.concatenate([self.foot_geoms, self.pad_geoms])
        self.contact_sign = np.where(np.isin(geoms[:, 1], robot), 1.0, -1.0).astype(np.float32)
        dims = np.asarray(d._impl.contact.dim) if hasattr(d._impl.contact, "dim") else None
        if dims is not None and not np.all(dims == 3):
            raise RuntimeError("hexjax expects condim 3 on every contact pair")
        self.nefc = int(d._impl.efc_J.shape[0])

    @functools.cached_property
    def env_geoms(self):
        """The jitted, vmapped per-env slot assignment of `batch_model`: terrain -> (geom_pos, geom_size) with a
        leading batch axis. One program instead of a few hundred eager ops, each compiled on its own (3.5 s on
        2 cores, again after every `jax.clear_caches`); made on first use, so building a model traces nothing."""
        feet = jnp.asarray(neutral_feet_body(self.robot)[:, :2])

        def one(t):
            m = env_model(self, t, *assign_slots(self, t, feet, jnp.zeros(2)))
            return m.geom_pos, m.geom_size

        return jax.jit(jax.vmap(one))

    def make_data(self, batch: int = 1):
        """An empty mjx.Data of the engine's (MuJoCo Warp's contact pool is shared by the worlds of a vmap of
        size `batch`, so it is sized for all of them)."""
        return self.engine.make_data(self, batch)

    def warp_pools(self, batch: int = 1) -> dict:
        """MuJoCo Warp's pool sizes for `batch` worlds: contacts shared by all worlds (`naconmax`), constraint rows
        per world (`njmax`), from the JAX implementation's fixed counts."""
        return {"naconmax": max(1, self.ncon) * batch, "njmax": max(1, self.nefc)}

    def init_data(self, torso_xy_yaw, template=None):
        """mjx.Data in the neutral stance at (x, y, yaw) (3,) on flat ground (`template`: from `make_data`)."""
        x, y, yaw = torso_xy_yaw[0], torso_xy_yaw[1], torso_xy_yaw[2]
        qpos = jnp.asarray(self.qpos0)
        quat = jnp.stack([jnp.cos(yaw / 2), 0.0 * yaw, 0.0 * yaw, jnp.sin(yaw / 2)])
        qpos = qpos.at[0].set(x).at[1].set(y).at[3:7].set(quat)
        d = self.make_data() if template is None else template
        return d.replace(qpos=qpos, ctrl=jnp.asarray(self.ctrl0))


@functools.lru_cache(maxsize=16)
def built(robot: RobotSpec, physics: PhysicsConfig, engine) -> SimModel:
    """Cached `SimModel` of an engine (specs and engines are frozen dataclasses, so they key the cache);
    `hexjax.sim.engines.sim_model` takes the engine's name."""
    return SimModel(robot, physics, engine)


def _box_xy_distance(points, terrain: Terrain):
    """Horizontal distance from points (Q, 2) to every box footprint (M,): (Q, M) m, inf where invalid."""
    d = jnp.abs(points[:, None, :] - terrain.box_pos[None, :, :2]) - terrain.box_half[None, :, :2]
    dist = jnp.linalg.norm(jnp.maximum(d, 0.0), axis=-1)
    return jnp.where(terrain.box_valid[None, :], dist, jnp.inf)


def _k_smallest(x, k: int):
    """(values, indices) of the k smallest entries along the last axis, ascending, by k argmin passes
    (k <= 4 here, so cheaper than a sort and lowers to plain reductions on every backend)."""
    vals, idxs = [], []
    for _ in range(k):
        i = jnp.argmin(x, axis=-1)
        vals.append(jnp.take_along_axis(x, i[..., None], -1)[..., 0])
        idxs.append(i)
        x = jnp.where(jnp.arange(x.shape[-1]) == i[..., None], jnp.inf, x)
    return jnp.stack(vals, -1), jnp.stack(idxs, -1)


def assign_slots(sm: SimModel, terrain: Terrain, foot_xy, torso_xy):
    """Slot geom positions and sizes for one env: the `slots_per_leg` boxes nearest each foot and the
    `torso_slots` nearest the torso centre; unused slots are parked below the ground.

    foot_xy (6, 2), torso_xy (2,) -> (slot_pos (S, 3), slot_size (S, 3)), S = 6 * k + torso_slots."""
    k, kt = sm.physics.slots_per_leg, sm.physics.torso_slots
    groups = []  # (query points, slots per point, reach m)
    if k:
        groups.append((foot_xy, k, SLOT_REACH))
    if kt:
        groups.append((torso_xy[None], kt, 0.5 * sm.robot.body_length + SLOT_REACH))
    parked = jnp.array([0.0, 0.0, PARKED_Z])
    pos_out, size_out = [], []
    for pts, kk, reach in groups:
        # with fewer boxes than slots the extra passes return inf, so those slots are parked below
        dmin, idx = _k_smallest(_box_xy_distance(pts, terrain), kk)
        use = (dmin <= reach)[..., None]
        pos_out.append(jnp.where(use, terrain.box_pos[idx], parked).reshape(-1, 3))
        size_out.append(jnp.where(use, terrain.box_half[idx], 0.01).reshape(-1, 3))
    if not pos_out:
        return jnp.zeros((0, 3)), jnp.zeros((0, 3))
    return jnp.concatenate(pos_out), jnp.concatenate(size_out)


def slot_geom_ids(sm: SimModel) -> np.ndarray:
    return np.concatenate([sm.leg_slot_geoms.reshape(-1), sm.torso_slot_geoms])


def env_model(sm: SimModel, terrain: Terrain, slot_pos, slot_size, base=None):
    """The mjx.Model of one env: `base` (default the shared model) with its ground height and slots set."""
    m = sm.mjx_model if base is None else base
    ids = slot_geom_ids(sm)
    geom_pos = m.geom_pos.at[sm.ground_geom, 2].set(terrain.ground_z)
    if not ids.size:
        return m.replace(geom_pos=geom_pos)
    return sm.engine.place_slots(m, ids, geom_pos.at[ids].set(slot_pos), m.geom_size.at[ids].set(slot_size),
                                 slot_size)


def place_static_geoms(sm: SimModel, d, terrain: Terrain, slot_pos):
    """MuJoCo Warp computes world-frame poses of the world body's geoms once, in make_data, and never again,
    so moving a slot (or the ground) through the model's geom_pos does not move it there: its geom_xpos is
    set here as well (world geoms keep the identity orientation). Needed on the warp engine only."""
    ids = slot_geom_ids(sm)
    xpos = d.geom_xpos.at[sm.ground_geom, 2].set(terrain.ground_z)
    if ids.size:
        xpos = xpos.at[ids].set(slot_pos)
    return d.replace(geom_xpos=xpos)


def batch_model(sm: SimModel, terrain: Terrain):
    """Playground-style batching: (model with a leading batch axis on geom_pos / geom_size only,
    in_axes pytree for jax.vmap). Slots start at the boxes nearest the neutral stance at the origin."""
    geom_pos, geom_size = sm.env_geoms(terrain)
    in_axes = jax.tree_util.tree_map(lambda _: None, sm.mjx_model)
    in_axes = in_axes.replace(geom_pos=0, geom_size=0)
    shared = sm.mjx_model.replace(geom_pos=geom_pos, geom_size=geom_size)
    return shared, in_axes


def read_obs(sm: SimModel, sensors: SensorConfig, m, d) -> Obs:
    """Sensor readings of one env (see `Obs`). Contact forces come from the constraint solver's
    efc_force (pyramidal cone decoded as in MuJoCo's mj_contactForce)."""
    force, idx = contact_forces(m, d)
    frames = d._impl.contact.frame[idx]  # (n, 3, 3): rows normal, tangent1, tangent2
    world = jnp.einsum("ni,nij->nj", force[:, :3], frames) * jnp.asarray(sm.contact_sign[idx])[:, None]
    # now the force on the robot geom from the terrain, whichever side of the pair the robot geom is on
    foot_mask, pad_mask = jnp.asarray(sm.contact_foot[idx]), jnp.asarray(sm.contact_pad[idx])
    foot_force = foot_mask.T @ world  # (6, 3)
    foot_normal = foot_mask.T @ force[:, 0]
    pad_normal = pad_mask.T @ force[:, 0]
    return Obs(
        qpos=d.qpos[7:], qvel=d.qvel[6:], torso_pos=d.qpos[:3], torso_quat=d.qpos[3:7],
        foot_force=foot_force, foot_contact=foot_normal > sensors.contact_threshold,
        tactile_force=pad_normal, tactile=pad_normal > sensors.tactile_threshold, time=d.time)


def obs_from_sensordata(sensors: SensorConfig, qpos, qvel, sensordata, time) -> Obs:
    """`Obs` of one env from MuJoCo's own sensors (a model built with `contact_sensors=True`): what the
    MuJoCo Warp and MuJoCo C backends read. Foot force: the net force on the foot (world frame); normal forces:
    the sum of the first (normal) component over the foot's / pad's matched contacts. Same quantities as
    `read_obs`, which decodes the JAX solver's rows directly. Works on numpy or jax arrays."""
    lay = sensor_layout()
    legs = sensordata[..., :lay["actuator"]].reshape(sensordata.shape[:-1] + (N_LEGS, lay["per_leg"]))
    foot_force = legs[..., 0:3]
    each = lambda a: legs[..., a:a + 3 * SENSOR_MATCHES].reshape(legs.shape[:-1] + (SENSOR_MATCHES, 3))[..., 0]
    foot_normal = each(lay["foot_each"]).sum(-1)
    pad_normal = each(lay["pad_each"]).sum(-1)
    return Obs(qpos=qpos[..., 7:], qvel=qvel[..., 6:], torso_pos=qpos[..., :3], torso_quat=qpos[..., 3:7],
               foot_force=foot_force, foot_contact=foot_normal > sensors.contact_threshold,
               tactile_force=pad_normal, tactile=pad_normal > sensors.tactile_threshold, time=time)


def actuator_forces(sensordata):
    """The 18 actuator forces from sensordata (contact_sensors=True models)."""
    lay = sensor_layout()
    return sensordata[..., lay["actuator"]:lay["feet"]]


def foot_positions(sensordata):
    """The six foot sites' world positions (..., 6, 3) from sensordata (contact_sensors=True models)."""
    lay = sensor_layout()
    return sensordata[..., lay["feet"]:lay["size"]].reshape(sensordata.shape[:-1] + (N_LEGS, 3))
