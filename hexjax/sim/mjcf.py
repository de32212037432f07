"""MJCF generation for a `RobotSpec` plus the terrain collision slots the simulator swaps per env.

Contact is declared only through explicit <pair> elements (every geom has contype = conaffinity = 0),
so legs never collide with each other or with the torso, and MJX checks exactly these pairs:
  ground plane  x {6 feet (sphere), torso (box)}
                (no pad x ground pair: the pads sit >= 1.8 cm above the foot and sense obstacles; the
                 6 pairs cost 12 of 66 contact slots, ~1/6 of the solver's rows, for contacts that
                 only a collapsed leg would make)
  leg slot k of leg i x {foot i, pad i}          (k < slots_per_leg)
  torso slot k x torso                           (k < torso_slots)
A slot is a box geom of the world body whose position and size the rollout sets, each control step,
to one of the terrain boxes nearest to that leg (or the torso): see `hexjax.sim.model`.
"""

from __future__ import annotations

import math

from hexjax.sim.config import PhysicsConfig
from hexjax.world.robot import (LEG_NAMES, N_LEGS, RobotSpec, forward_sign, hip_positions, mount_yaws,
                                neutral_joint_angles)

PARKED_Z = -5.0  # where unused slots wait, far below the ground


def _f(*xs) -> str:
    return " ".join(f"{x:.6g}" for x in xs)


# Contact sensors (`contact_sensors=True`): per leg, the net terrain force on the foot (world frame, 3 values),
# then the contact-frame forces of up to SENSOR_MATCHES contacts of the foot and of the pad (normal first,
# SENSOR_MATCHES x 3 each), then 18 actuator forces, then each foot site's world position (6 x 3: the foot traces of
# MuJoCo C). `hexjax.sim.model.obs_from_sensordata` decodes them.
SENSOR_MATCHES = 4


def sensor_layout() -> dict:
    """Offsets into sensordata of the blocks `build_mjcf(..., contact_sensors=True)` declares."""
    per_leg = 3 + 2 * 3 * SENSOR_MATCHES
    actuator = N_LEGS * per_leg
    return dict(per_leg=per_leg, foot_net=0, foot_each=3, pad_each=3 + 3 * SENSOR_MATCHES,
                actuator=actuator, feet=actuator + 3 * N_LEGS, size=actuator + 6 * N_LEGS)


def option_xml(physics: PhysicsConfig, gravity=None) -> str:
    """The `<option>` element of a physics configuration (solver, cone, tolerances, timestep, integrator);
    `gravity` (3 numbers) where it is not MuJoCo's default (the analytic tests tilt it)."""
    g = f' gravity="{_f(*gravity)}"' if gravity is not None else ""
    integ = {"euler": "Euler", "implicitfast": "implicitfast"}[physics.integrator]
    return (f'<option timestep="{physics.timestep:.6g}" iterations="{physics.iterations}" '
            f'ls_iterations="{physics.ls_iterations}" tolerance="{physics.tolerance:.6g}" '
            f'ls_tolerance="{physics.ls_tolerance:.6g}" impratio="{physics.impratio:.6g}" solver="Newton" '
            f'cone="{physics.cone}" integrator="{integ}"{g}><flag eulerdamp="disable"/></option>')


def _legs(spec: RobotSpec, bits, leg_mass: float) -> list:
    """Each leg's bodies: coxa, femur and tibia capsules, the tibia's pad and foot (their masses shares of
    `leg_mass`), the foot's site."""
    hips, yaws, fsign = hip_positions(spec), mount_yaws(spec), forward_sign()
    lc, lf, lt = spec.coxa_length, spec.femur_length, spec.tibia_length
    legs = []
    for i, name in enumerate(LEG_NAMES):
        p0, p1 = spec.pad_span
        pad_y = fsign[i] * spec.pad_offset
        legs.append(f"""
      <body name="{name}_coxa" pos="{_f(*hips[i])}" euler="0 0 {yaws[i]:.6g}">
        <joint name="{name}_coxa" axis="0 0 1" range="{_f(*spec.coxa_range)}"/>
        <geom name="{name}_coxa" type="capsule" fromto="0 0 0 {lc:.6g} 0 0" size="0.01" mass="{0.25 * leg_mass:.6g}"/>
        <body name="{name}_femur" pos="{lc:.6g} 0 0">
          <joint name="{name}_femur" axis="0 -1 0" range="{_f(*spec.femur_range)}"/>
          <geom name="{name}_femur" type="capsule" fromto="0 0 0 {lf:.6g} 0 0" size="0.009" mass="{0.35 * leg_mass:.6g}"/>
          <body name="{name}_tibia" pos="{lf:.6g} 0 0">
            <joint name="{name}_tibia" axis="0 -1 0" range="{_f(*spec.tibia_range)}"/>
            <geom name="{name}_tibia" type="capsule" fromto="0 0 0 {lt - spec.foot_radius:.6g} 0 0" size="0.007" mass="{0.3 * leg_mass:.6g}"/>
            <geom name="{name}_pad" type="capsule" fromto="{p0 * lt:.6g} {pad_y:.6g} 0 {p1 * lt:.6g} {pad_y:.6g} 0" size="{spec.pad_radius:.6g}" mass="{0.02 * leg_mass:.6g}" rgba="0.9 0.3 0.2 1"{bits(2)}/>
            <geom name="{name}_foot" type="sphere" pos="{lt:.6g} 0 0" size="{spec.foot_radius:.6g}" mass="{0.08 * leg_mass:.6g}" rgba="0.2 0.2 0.2 1"{bits(1)}/>
            <site name="{name}_foot" pos="{lt:.6g} 0 0" size="0.005"/>
          </body>
        </body>
      </body>""")
    return legs


def _slots(physics: PhysicsConfig, terrain_boxes: int) -> list:
    """The terrain's box geoms: per-leg and torso slots, or the world body's grid of `terrain_boxes`."""
    slots = []
    for i, name in enumerate(LEG_NAMES):
        for k in range(physics.slots_per_leg):
            slots.append(f'<geom name="slot_{name}_{k}" type="box" size="0.01 0.01 0.01" pos="0 0 {PARKED_Z}" rgba="0.6 0.5 0.3 1"/>')
    for k in range(physics.torso_slots):
        slots.append(f'<geom name="slot_torso_{k}" type="box" size="0.01 0.01 0.01" pos="0 0 {PARKED_Z}" rgba="0.6 0.5 0.3 1"/>')
    k = math.ceil(math.sqrt(terrain_boxes))
    for j in range(terrain_boxes):
        # world-body geoms: no body of their own, so neither the broadphase's sweep nor the kinematics of bodies
        # sees them; the world body's tree (built here from this grid) prunes them
        slots.append(f'<geom name="terrain_{j}" type="box" size="0.01 0.01 0.01" pos="{j // k} {j % k} {PARKED_Z}" '
                     f'conaffinity="3" rgba="0.6 0.5 0.3 1"/>')
    return slots


def _sensors() -> list:
    """Contact, actuator-force and foot-position sensors (`sensor_layout`), for engines other than MJX's JAX one."""
    sensors = []
    for name in LEG_NAMES:
        # geom2=g with reduce=netforce: the net force on g from everything it touches, world frame
        sensors.append(f'<contact name="{name}_foot_net" geom2="{name}_foot" data="force" reduce="netforce" num="1"/>')
        sensors.append(f'<contact name="{name}_foot_each" geom1="{name}_foot" data="force" reduce="maxforce" '
                       f'num="{SENSOR_MATCHES}"/>')
        sensors.append(f'<contact name="{name}_pad_each" geom1="{name}_pad" data="force" reduce="maxforce" '
                       f'num="{SENSOR_MATCHES}"/>')
    for name in LEG_NAMES:
        for j in ("coxa", "femur", "tibia"):
            sensors.append(f'<actuatorfrc name="{name}_{j}_force" actuator="{name}_{j}"/>')
    for name in LEG_NAMES:
        sensors.append(f'<framepos name="{name}_foot_pos" objtype="site" objname="{name}_foot"/>')
    return sensors


def _pairs(physics: PhysicsConfig) -> list:
    """The explicit contact pairs: ground with feet and torso, each slot with its leg's foot and pad or the torso."""
    pairs = []
    for name in LEG_NAMES:
        pairs.append(f'<pair geom1="ground" geom2="{name}_foot"/>')
    pairs.append('<pair geom1="ground" geom2="torso"/>')
    for name in LEG_NAMES:
        for k in range(physics.slots_per_leg):
            pairs.append(f'<pair geom1="slot_{name}_{k}" geom2="{name}_foot"/>')
            pairs.append(f'<pair geom1="slot_{name}_{k}" geom2="{name}_pad"/>')
    for k in range(physics.torso_slots):
        pairs.append(f'<pair geom1="slot_torso_{k}" geom2="torso"/>')
    return pairs


def _actuators(spec: RobotSpec) -> list:
    """A position servo per joint with the robot's gains and torque limit."""
    actuators = []
    for name in LEG_NAMES:
        for j in ("coxa", "femur", "tibia"):
            actuators.append(
                f'<position name="{name}_{j}" joint="{name}_{j}" kp="{spec.kp:.6g}" kv="{spec.kv:.6g}" '
                f'forcerange="{-spec.max_torque:.6g} {spec.max_torque:.6g}"/>')
    return actuators


def build_mjcf(spec: RobotSpec, physics: PhysicsConfig, *, contact_sensors: bool = False,
               terrain_boxes: int = 0) -> str:
    """MJCF text of the robot on a ground plane with `physics.slots_per_leg` slots per leg.

    contact_sensors: declare MuJoCo contact and actuator-force sensors (see `sensor_layout`), so that an
    engine other than MJX's JAX one (MuJoCo Warp, MuJoCo C) computes the same observations.
    terrain_boxes: instead of slots, declare this many box geoms `terrain_<j>` in the world body, parked below
    the ground on a square grid (box j in column j // k, row j % k, k = ceil(sqrt(terrain_boxes)), 1 m apart), so
    that the compiled bounding-volume tree of the world body splits the grid into blocks of neighbouring slots
    (MuJoCo C fills the slots with each env's boxes and refits that tree: `hexjax.sim.engines.c_models`). They collide
    with the feet, pads and torso through contype / conaffinity, that is through MuJoCo's own broadphase and
    mid-phase tree. Needs slots_per_leg = torso_slots = 0. The contact parameters equal the slot pairs':
    condim 3, the robot's friction, default solref / solimp, no margin."""
    spec.validate()
    physics.validate()
    if terrain_boxes and (physics.slots_per_leg or physics.torso_slots):
        raise ValueError(f"build_mjcf: terrain_boxes={terrain_boxes} needs physics.slots_per_leg = torso_slots = 0, "
                         f"got {physics.slots_per_leg}, {physics.torso_slots}")
    # broadphase bits: feet and torso collide with conaffinity bit 1, pads with bit 2; terrain boxes carry both,
    # the ground neither (its contacts are the explicit pairs below, as in the slot model: no pad x ground)
    bits = (lambda ct: f' contype="{ct}"') if terrain_boxes else (lambda ct: "")
    leg_mass = spec.total_mass * spec.leg_mass_fraction / N_LEGS
    torso_mass = spec.total_mass - N_LEGS * leg_mass
    q0 = neutral_joint_angles(spec)
    z0 = spec.hip_height + 0.003

    legs = _legs(spec, bits, leg_mass)

    slots = _slots(physics, terrain_boxes)
    sensors = _sensors() if contact_sensors else []
    pairs = _pairs(physics)
    actuators = _actuators(spec)

    qpos0 = _f(0, 0, z0, 1, 0, 0, 0, *q0.reshape(-1))
    body = "\n".join(legs)
    return f"""<mujoco model="hexjax_{spec.name}">
  <compiler angle="radian" autolimits="true"/>
  {option_xml(physics)}
  <default>
    <geom contype="0" conaffinity="0" friction="{spec.friction:.6g} 0.005 0.0001" condim="3"/>
    <joint damping="{spec.joint_damping:.6g}" armature="{spec.armature:.6g}"/>
    <pair condim="3" friction="{spec.friction:.6g} {spec.friction:.6g} 0.005 0.0001 0.0001"/>
  </default>
  <worldbody>
    <light pos="0 0 3" dir="0 0 -1" directional="true"/>
    <geom name="ground" type="plane" size="0 0 0.05" rgba="0.8 0.85 0.8 1"/>
    {chr(10).join('    ' + s for s in slots)}
    <body name="torso" pos="0 0 {z0:.6g}">
      <freejoint name="root"/>
      <geom name="torso" type="box" size="{_f(spec.body_length / 2, spec.body_width / 2, spec.body_thickness / 2)}" mass="{torso_mass:.6g}" rgba="0.3 0.4 0.7 1"{bits(1)}/>
      <site name="imu" pos="0 0 0" size="0.01"/>{body}
    </body>
  </worldbody>
  <actuator>
    {chr(10).join('    ' + a for a in actuators)}
  </actuator>
  <contact>
    {chr(10).join('    ' + p for p in pairs)}
  </contact>
  <sensor>
    {chr(10).join('    ' + x for x in sensors)}
  </sensor>
  <keyframe>
    <key name="stance" qpos="{qpos0}" ctrl="{_f(*q0.reshape(-1))}"/>
  </keyframe>
</mujoco>
"""


def compile_mjcf(xml: str):
    """An MjModel of `build_mjcf`'s XML whose ground plane follows later writes to its geom_pos.

    Compiled at the world frame's origin, the plane is marked as sharing its body's frame (geom_sameframe), and
    MuJoCo's mj_kinematics then places it there whatever geom_pos says: a model that moves the plane per env to
    the terrain's ground_z (the MuJoCo C backend, the bench's mj_step reference) kept it at z = 0, which filled
    Yu 2019's ditches and the lowered terrain families. MJX does not read the flag; its models are unchanged."""
    import mujoco
    m = mujoco.MjModel.from_xml_string(xml)
    m.geom_sameframe[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "ground")] = mujoco.mjtSameFrame.mjSAMEFRAME_NONE
    return m
