"""Per-env randomisation of dynamics, sensing and faults: the ranges (`RandomizationSpec`, data: a YAML
`randomization:` block) and one draw per env (`Perturbation`), sampled the way terrains are
(`hexjax.world.terrain.sample`). The rollout applies a batch of draws inside its control step
(`rollout(..., perturbation=...)`, `hexjax.sim.perturb`).

Every field of a draw is an array, so one compiled rollout serves every range, every draw and every cell of a
sweep (`hexjax robustness` runs a whole sweep as one batch); a rollout without a perturbation is the program
it always was. The float fields are differentiable on the MJX path.

Keys of a `randomization:` block (all optional; a range is [low, high], drawn uniformly and independently per
env; a single number v means [v, v]):

  friction          sliding friction of every robot-terrain contact pair (the robot's own when absent;
                    MuJoCo Playground's Go1 draws U(0.4, 1.0))
  torso_mass_scale  factor on the torso's mass and inertia
  payload_kg        a point mass carried on the torso, kg
  payload_offset_m  its offset from the torso's centre of mass in the torso frame: x and y each drawn in the
                    range (Playground: +-5 cm CoM shifts), z = 0
  kp_scale          factor on every servo's gains (position gain kp and velocity gain kv)
  torque_scale      factor on every servo's torque limit
  damping_scale     factor on every joint's damping
  latency_steps     whole control steps between the controller's output and the servos (integers 0 ... 8)
  force_noise_n     standard deviation of Gaussian noise on each foot-force component, N, every control step
  force_bias_n      an offset per env, leg and axis, drawn in the range, N
  force_dropout     probability that a leg's force reading is lost in a control step (reads 0, no contact)
  tactile_noise_n, tactile_bias_n, tactile_dropout   the same for the shin pads' normal forces
  fault             a leg fault from a time on: {kind: locked | limp | sensor_dead, legs: [0, ..., 5] (one drawn
                    per env, leg order LF LM LH RF RM RH), time_s: [low, high] after the walk starts,
                    probability: p (share of envs with the fault)}. locked: the leg's servos hold the angles
                    they had at that time; limp: its servos give no torque; sensor_dead: its foot and pad
                    read nothing.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, Dict, Mapping, Optional, Tuple

import numpy as np

MAX_LATENCY = 8  # control steps; the rollout keeps this many past actions per env when perturbed
FAULT_KINDS = ("none", "locked", "limp", "sensor_dead")
Range = Tuple[float, float]

# key -> (lowest allowed value, highest allowed value, what it is) for the range keys
_LIMITS = {
    "friction": (0.0, 10.0, "friction coefficient"),
    "torso_mass_scale": (1e-3, 100.0, "factor"),
    "payload_kg": (0.0, 1000.0, "kg"),
    "payload_offset_m": (-1.0, 1.0, "m"),
    "kp_scale": (0.0, 100.0, "factor"),
    "torque_scale": (0.0, 100.0, "factor"),
    "damping_scale": (0.0, 1000.0, "factor"),
    "latency_steps": (0.0, float(MAX_LATENCY), "control steps"),
    "force_noise_n": (0.0, 1e4, "N"),
    "force_bias_n": (-1e4, 1e4, "N"),
    "force_dropout": (0.0, 1.0, "probability"),
    "tactile_noise_n": (0.0, 1e4, "N"),
    "tactile_bias_n": (-1e4, 1e4, "N"),
    "tactile_dropout": (0.0, 1.0, "probability"),
}
# a draw of the neutral value changes nothing
NEUTRAL = {"torso_mass_scale": 1.0, "payload_kg": 0.0, "payload_offset_m": 0.0, "kp_scale": 1.0,
           "torque_scale": 1.0, "damping_scale": 1.0, "latency_steps": 0.0, "force_noise_n": 0.0,
           "force_bias_n": 0.0, "force_dropout": 0.0, "tactile_noise_n": 0.0, "tactile_bias_n": 0.0,
           "tactile_dropout": 0.0}


@dataclasses.dataclass(frozen=True)
class FaultSpec:
    """A leg fault (module docstring): kind, the legs one is drawn from, the onset window and the share of envs."""

    kind: str = "locked"
    legs: Tuple[int, ...] = (0, 1, 2, 3, 4, 5)
    time_s: Range = (0.0, 0.0)
    probability: float = 1.0

    def validate(self, prefix: str = "randomization.fault"):
        if self.kind not in FAULT_KINDS[1:]:
            raise ValueError(f"{prefix}.kind={self.kind!r}: use one of {FAULT_KINDS[1:]}")
        if not self.legs or any(not (0 <= int(g) <= 5) for g in self.legs):
            raise ValueError(f"{prefix}.legs={list(self.legs)!r}: leg indices 0-5 (LF LM LH RF RM RH), at least one")
        lo, hi = self.time_s
        if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo <= hi):
            raise ValueError(f"{prefix}.time_s={list(self.time_s)!r}: need 0 <= low <= high (s after the walk starts)")
        if not (0.0 <= self.probability <= 1.0):
            raise ValueError(f"{prefix}.probability={self.probability!r}: must be in [0, 1]")


@dataclasses.dataclass(frozen=True)
class RandomizationSpec:
    """Ranges of the per-env randomisation (module docstring); None: that quantity is not randomised."""

    friction: Optional[Range] = None
    torso_mass_scale: Optional[Range] = None
    payload_kg: Optional[Range] = None
    payload_offset_m: Optional[Range] = None
    kp_scale: Optional[Range] = None
    torque_scale: Optional[Range] = None
    damping_scale: Optional[Range] = None
    latency_steps: Optional[Range] = None
    force_noise_n: Optional[Range] = None
    force_bias_n: Optional[Range] = None
    force_dropout: Optional[Range] = None
    tactile_noise_n: Optional[Range] = None
    tactile_bias_n: Optional[Range] = None
    tactile_dropout: Optional[Range] = None
    fault: Optional[FaultSpec] = None

    def validate(self, prefix: str = "randomization"):
        for key, (lo_ok, hi_ok, unit) in _LIMITS.items():
            r = getattr(self, key)
            if r is None:
                continue
            if len(r) != 2:
                raise ValueError(f"{prefix}.{key}={list(r)!r}: give [low, high] or one number")
            lo, hi = r
            if not (math.isfinite(lo) and math.isfinite(hi)):
                raise ValueError(f"{prefix}.{key}={list(r)!r}: must be finite")
            if lo > hi:
                raise ValueError(f"{prefix}.{key}={list(r)!r}: low > high")
            if lo < lo_ok or hi > hi_ok:
                raise ValueError(f"{prefix}.{key}={list(r)!r}: must lie in [{lo_ok:g}, {hi_ok:g}] ({unit})")
            if key == "latency_steps" and (lo != int(lo) or hi != int(hi)):
                raise ValueError(f"{prefix}.{key}={list(r)!r}: whole control steps")
        if self.fault is not None:
            self.fault.validate(f"{prefix}.fault")
        return self

    def check_horizon(self, duration: float, prefix: str = "randomization"):
        """A fault whose earliest onset lies past the walk's `duration` s would never act: refused."""
        if self.fault is not None and self.fault.time_s[0] >= duration:
            raise ValueError(f"{prefix}.fault.time_s={list(self.fault.time_s)!r}: starts at or after the "
                             f"{duration:g} s walk ends")

    def with_value(self, key: str, value: float) -> "RandomizationSpec":
        """This spec with one range key set to the point `value` (`fault_time_s` / `fault_probability`
        set the fault's); what a sweep axis does per cell."""
        if key.startswith("fault_"):
            if self.fault is None:
                raise ValueError(f"randomization.{key}: no fault in the randomization to set it on")
            sub = key[len("fault_"):]
            if sub not in ("time_s", "probability"):
                raise ValueError(f"randomization.{key}: unknown; a sweep sets fault_time_s or fault_probability")
            v = (float(value), float(value)) if sub == "time_s" else float(value)
            return dataclasses.replace(self, fault=dataclasses.replace(self.fault, **{sub: v})).validate()
        if key not in _LIMITS:
            raise ValueError(f"randomization.{key}: unknown key; known: {', '.join(list(_LIMITS))}")
        return dataclasses.replace(self, **{key: (float(value), float(value))}).validate()

    def to_dict(self) -> Dict[str, Any]:
        out = {k: list(getattr(self, k)) for k in _LIMITS if getattr(self, k) is not None}
        if self.fault is not None:
            f = self.fault
            out["fault"] = dict(kind=f.kind, legs=list(f.legs), time_s=list(f.time_s), probability=f.probability)
        return out


AXES = tuple(_LIMITS) + ("fault_time_s", "fault_probability")


def randomization_from_dict(raw: Optional[Mapping[str, Any]], source: str = "randomization",
                            prefix: str = "randomization") -> RandomizationSpec:
    """A checked `RandomizationSpec` from a mapping (e.g. a YAML `randomization:` block). A single number for a
    range means [v, v]. Every error is one ValueError line naming source, key and value."""
    from hexjax.world.files import build
    if raw is None:
        return RandomizationSpec()
    if not isinstance(raw, Mapping):
        raise ValueError(f"{source}: {prefix}={raw!r}: must be a mapping of keys")
    raw = dict(raw)
    for k, v in list(raw.items()):
        if k in _LIMITS and isinstance(v, (int, float)) and not isinstance(v, bool):
            raw[k] = [v, v]
    fault = raw.pop("fault", None)
    spec = build(RandomizationSpec, raw, source, prefix)
    if fault is not None:
        if not isinstance(fault, Mapping):
            raise ValueError(f"{source}: {prefix}.fault={fault!r}: must be a mapping (kind, legs, time_s, probability)")
        fault = dict(fault)
        if isinstance(fault.get("time_s"), (int, float)) and not isinstance(fault.get("time_s"), bool):
            fault["time_s"] = [fault["time_s"], fault["time_s"]]
        if isinstance(fault.get("legs"), int) and not isinstance(fault.get("legs"), bool):
            fault["legs"] = [fault["legs"]]
        f = build(FaultSpec, fault, source, f"{prefix}.fault")
        try:
            f.validate(f"{prefix}.fault")
        except ValueError as err:
            raise ValueError(f"{source}: {err}") from None
        spec = dataclasses.replace(spec, fault=f)
    return spec


@functools.lru_cache(maxsize=1)
def _perturbation_class():
    from flax import struct

    @struct.dataclass
    class Perturbation:
        """One draw per env (leading axis B when batched). friction < 0: the model's own.

        friction (), torso_mass_scale (), payload_kg (), payload_offset (3,) m, kp_scale (), torque_scale (),
        damping_scale (), latency () int32 control steps, force_noise () N, force_bias (6, 3) N,
        force_dropout (), tactile_noise () N, tactile_bias (6,) N, tactile_dropout (),
        fault_kind () int32 (index into FAULT_KINDS), fault_leg () int32, fault_time () s after the walk
        starts, key (2,) uint32: the env's stream of sensor noise and dropout."""

        friction: Any
        torso_mass_scale: Any
        payload_kg: Any
        payload_offset: Any
        kp_scale: Any
        torque_scale: Any
        damping_scale: Any
        latency: Any
        force_noise: Any
        force_bias: Any
        force_dropout: Any
        tactile_noise: Any
        tactile_bias: Any
        tactile_dropout: Any
        fault_kind: Any
        fault_leg: Any
        fault_time: Any
        key: Any

    return Perturbation


def __getattr__(name):  # Perturbation is made on first use, so importing this module loads no JAX
    if name == "Perturbation":
        return _perturbation_class()
    raise AttributeError(name)


def _bounds(spec: RandomizationSpec) -> np.ndarray:
    """(len(_LIMITS), 2) float32 [low, high] per range key; an absent key gives its neutral value (friction:
    -1, the model's own)."""
    rows = []
    for k in _LIMITS:
        r = getattr(spec, k)
        rows.append(r if r is not None else (NEUTRAL.get(k, -1.0),) * 2)
    return np.asarray(rows, np.float32)


def _fault_arrays(spec: RandomizationSpec):
    """(kind int32, leg mask (6,) bool, onset [low, high] float32, probability float32) of the spec's fault."""
    f = spec.fault
    if f is None:
        return np.int32(0), np.ones(6, bool), np.zeros(2, np.float32), np.float32(0.0)
    mask = np.zeros(6, bool)
    mask[list(f.legs)] = True
    return np.int32(FAULT_KINDS.index(f.kind)), mask, np.asarray(f.time_s, np.float32), np.float32(f.probability)


@functools.lru_cache(maxsize=1)
def _draw_fn():
    """The jitted, vmapped draw: every range and the fault are arguments, so one program serves every spec."""
    import jax
    import jax.numpy as jnp
    P = __getattr__("Perturbation")
    col = {k: i for i, k in enumerate(_LIMITS)}

    def one(bounds, kind, legs, onset, prob, key, i):
        k = jax.random.split(jax.random.fold_in(key, i), 16)

        def u(name, j, shape=()):
            lo, hi = bounds[col[name], 0], bounds[col[name], 1]
            return lo + (hi - lo) * jax.random.uniform(k[j], shape)

        lo_lat, hi_lat = bounds[col["latency_steps"]].astype(jnp.int32)
        has = jax.random.uniform(k[13]) < prob
        leg = jax.random.categorical(k[14], jnp.where(legs, 0.0, -jnp.inf)).astype(jnp.int32)
        return P(friction=u("friction", 0), torso_mass_scale=u("torso_mass_scale", 1),
                 payload_kg=u("payload_kg", 2),
                 payload_offset=jnp.concatenate([u("payload_offset_m", 3, (2,)), jnp.zeros(1)]),
                 kp_scale=u("kp_scale", 4), torque_scale=u("torque_scale", 5), damping_scale=u("damping_scale", 6),
                 latency=jax.random.randint(k[7], (), lo_lat, hi_lat + 1).astype(jnp.int32),
                 force_noise=u("force_noise_n", 8), force_bias=u("force_bias_n", 9, (6, 3)),
                 force_dropout=u("force_dropout", 10), tactile_noise=u("tactile_noise_n", 11),
                 tactile_bias=u("tactile_bias_n", 12, (6,)),
                 tactile_dropout=u("tactile_dropout", 15),
                 fault_kind=jnp.where(has, kind, 0).astype(jnp.int32), fault_leg=leg,
                 fault_time=jnp.where(has, onset[0] + (onset[1] - onset[0]) * jax.random.uniform(jax.random.fold_in(k[14], 1), ()), jnp.inf),
                 key=jax.random.fold_in(key, i + 2 ** 30))

    return jax.jit(jax.vmap(one, in_axes=(None,) * 6 + (0,)))


def sample_perturbation(spec: RandomizationSpec, key, n: int):
    """`n` draws (a batched `Perturbation`) of `spec`. Env i draws from `fold_in(key, i)` alone, so a draw
    reproduces from (spec, key, i) whatever n is."""
    import jax.numpy as jnp
    spec.validate()
    if isinstance(n, bool) or not (isinstance(n, (int, np.integer)) and n >= 1):
        raise ValueError(f"n={n!r}: the number of draws must be a whole number >= 1")
    kind, legs, onset, prob = _fault_arrays(spec)
    return _draw_fn()(jnp.asarray(_bounds(spec)), kind, legs, onset, prob, key, jnp.arange(n))


def concat_perturbations(parts):
    """Batched perturbations joined along the env axis (the cells of a sweep, for one rollout call)."""
    import jax
    import jax.numpy as jnp
    return jax.tree_util.tree_map(lambda *a: jnp.concatenate(a), *parts)
