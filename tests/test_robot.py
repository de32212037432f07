import dataclasses

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from hexjax.sim.config import PhysicsConfig
from hexjax.sim.mjcf import build_mjcf
from hexjax.world.presets import get_robot, luneckas2020, yu2019
from hexjax.world.robot import LEG_NAMES, leg_fk, leg_ik, neutral_feet_body, neutral_feet_leg_frame


@pytest.mark.parametrize("spec", [luneckas2020(), yu2019()])
def test_fk_ik_roundtrip_jit_vmap(spec):
    key = jax.random.PRNGKey(0)
    q = jax.random.uniform(key, (256, 3), minval=jnp.array([-0.8, -0.6, -2.2]), maxval=jnp.array([0.8, 0.8, -0.5]))
    p = jax.jit(jax.vmap(lambda x: leg_fk(spec, x)))(q)
    q2, ok = jax.jit(jax.vmap(lambda x: leg_ik(spec, x)))(p)
    assert bool(ok.all())
    np.testing.assert_allclose(np.asarray(q2), np.asarray(q), atol=2e-4)  # rad


def test_reach_check_flags_far_and_near_targets():
    spec = luneckas2020()
    far = jnp.array([spec.coxa_length + spec.femur_length + spec.tibia_length + 0.02, 0.0, 0.0])
    near = jnp.array([spec.coxa_length + 0.0, 0.0, 0.0])
    _, ok_far = jax.jit(lambda p: leg_ik(spec, p))(far)
    _, ok_near = jax.jit(lambda p: leg_ik(spec, p))(near)
    q, ok = jax.jit(lambda p: leg_ik(spec, p))(jnp.asarray(neutral_feet_leg_frame(spec)[0]))
    assert not bool(ok_far) and not bool(ok_near) and bool(ok)
    assert np.all(np.isfinite(np.asarray(q)))


def test_mjcf_matches_spec_and_kinematics():
    spec = luneckas2020()
    m = mujoco.MjModel.from_xml_string(build_mjcf(spec, PhysicsConfig()))
    assert m.body_subtreemass[1] == pytest.approx(1.5, rel=1e-6)  # kg, seed 000
    assert m.nu == 18 and m.nq == 7 + 18
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, 0)
    mujoco.mj_forward(m, d)
    for i, n in enumerate(LEG_NAMES):
        sid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, f"{n}_foot")
        expect = neutral_feet_body(spec)[i] + d.qpos[:3]
        np.testing.assert_allclose(d.site_xpos[sid], expect, atol=1e-5)
    # torso bottom 8 cm above the ground with feet on it (seed 000)
    assert d.qpos[2] - spec.body_thickness / 2 == pytest.approx(0.08, abs=0.005)


def test_contact_pairs_only_terrain_against_feet_pads_torso():
    spec = luneckas2020()
    m = mujoco.MjModel.from_xml_string(build_mjcf(spec, PhysicsConfig(slots_per_leg=2, torso_slots=2)))
    names = lambda g: mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_GEOM, g)
    assert np.all(m.geom_contype == 0) and np.all(m.geom_conaffinity == 0)
    for g1, g2 in zip(m.pair_geom1, m.pair_geom2):
        a, b = names(g1), names(g2)
        assert a == "ground" or a.startswith("slot_")
        assert b == "torso" or b.endswith("_foot") or b.endswith("_pad")
        if a.startswith("slot_") and b != "torso":
            assert a.split("_")[1] == b.split("_")[0]  # a leg's slots touch only that leg
    assert m.npair == 7 + 2 * 6 * 2 + 2


def test_tactile_pad_is_in_front_of_each_shin():
    spec = luneckas2020()
    m = mujoco.MjModel.from_xml_string(build_mjcf(spec, PhysicsConfig()))
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, 0)
    mujoco.mj_forward(m, d)
    for n in LEG_NAMES:
        pad = d.geom_xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"{n}_pad")]
        tib = d.geom_xpos[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, f"{n}_tibia")]
        assert pad[0] - tib[0] > 0.008, n  # m, towards +x (walking direction)


@pytest.mark.parametrize("field,value,match", [
    ("femur_length", -0.05, "femur_length"),
    ("tibia_length", 0.0, "tibia_length"),
    ("stance_radial", 0.4, "out of reach"),
    ("coxa_range", (0.5, -0.5), "coxa_range"),
])
def test_invalid_robot_specs_raise(field, value, match):
    with pytest.raises(ValueError, match=match):
        dataclasses.replace(luneckas2020(), **{field: value}).validate()


def test_unknown_robot_preset():
    with pytest.raises(ValueError, match="nope"):
        get_robot("nope")
