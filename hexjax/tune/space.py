"""Tunable parameter spaces: which controller numbers an optimiser may move, within which bounds, and the
reparametrisation that keeps every iterate physical.

An optimiser works on unconstrained arrays u; a bounded field is p = lo + (hi - lo) sigmoid(u) (two-sided)
or p = lo + softplus(u) (one-sided, hi = None), so Adam's steps can never produce a negative height or a
threshold outside its range. Fields are named by their attribute path in the controller's params pytree
(`overcome_height`, `lc_trim`, `net.k`); a field may be an array (every entry gets the same bounds).

Presets follow the papers' hand rules and the robots' reach:
- "tactile" (Luneckas 2020, `TactileGaitController`): l_i, h_i, l_k, h_k, the swing slot (gait period / T) and
  the pad threshold;
- "cpg" (Yu 2019, `CPGController`): the linear converters' trims (g, h per joint, swing and stance), the
  F_contact thresholds, T_s, and the elevator's regenerated clearance; named in a config, also each leg's own
  trims, clearance offset and threshold factors (`PER_LEG`, 96 numbers);
- "cpg-reflex" (`hexjax.control.reflex` over the CPG): the reflex layer's weights, `net`, unbounded (`Free`: p = u,
  over every array of the field's pytree); named in a config, also the CPG's fields as `base.<field>`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Dict, Mapping, Optional

import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class Bound:
    """lo <= p <= hi (hi None: p >= lo only), in the field's SI units."""

    lo: float
    hi: Optional[float] = None

    def validate(self, name: str) -> None:
        if not math.isfinite(self.lo):
            raise ValueError(f"params.{name}.min={self.lo!r}: must be finite")
        if self.hi is not None and not (math.isfinite(self.hi) and self.hi > self.lo):
            raise ValueError(f"params.{name}: min={self.lo!r} must be < max={self.hi!r} (both finite)")


@dataclasses.dataclass(frozen=True)
class Free:
    """No bound: p = u, for a field that is a pytree of arrays (a network's weights)."""

    def validate(self, name: str) -> None:
        pass


def _softplus_inv(x):
    # log(exp(x) - 1), written to stay finite for large x
    return x + jnp.log(-jnp.expm1(-x))


def to_physical(u, b: Bound):
    """Unconstrained u -> bounded p (sigmoid to [lo, hi], or lo + softplus; `Free`: u itself)."""
    if isinstance(b, Free):
        return u
    if b.hi is None:
        return b.lo + jax.nn.softplus(u)
    # the clip only removes float32 rounding past a bound (its gradient there is ~0 anyway)
    return jnp.clip(b.lo + (b.hi - b.lo) * jax.nn.sigmoid(u), b.lo, b.hi)


def to_unconstrained(p, b: Bound, margin: float = 1e-6):
    """Inverse of `to_physical`; p is pulled inside the open interval by `margin` (relative) first."""
    if isinstance(b, Free):
        return jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32), p)
    p = jnp.asarray(p, jnp.float32)
    if b.hi is None:
        return _softplus_inv(jnp.maximum(p - b.lo, margin * max(1.0, abs(b.lo))))
    width = b.hi - b.lo
    f = jnp.clip((p - b.lo) / width, margin, 1 - margin)
    return jnp.log(f) - jnp.log1p(-f)


def _get(obj, path: str):
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


def _set(obj, path: str, value):
    head, _, rest = path.partition(".")
    if not rest:
        return obj.replace(**{head: value})
    return obj.replace(**{head: _set(getattr(obj, head), rest, value)})


def _has(obj, path: str) -> bool:
    try:
        _get(obj, path)
        return True
    except AttributeError:
        return False


def with_values(params, values: Mapping[str, Any], source: str = "params"):
    """`params` with the fields named in `values` (dotted names, as in a tuning log's "params") set to those
    numbers, each checked for existence, shape and finiteness first; raises one ValueError line naming the
    field."""
    for name, v in values.items():
        if not _has(params, name):
            raise ValueError(f"{source}: {name}: unknown parameter for this controller")
        if isinstance(_get(params, name), Mapping):  # a pytree field (`Free`): its arrays in the same tree
            params = _set(params, name, _tree_values(_get(params, name), v, f"{source}: {name}"))
            continue
        old = jnp.asarray(_get(params, name))
        try:
            new = np.asarray(v, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"{source}: {name}={v!r}: must be a number or an array of numbers") from None
        if new.shape != old.shape or not np.all(np.isfinite(new)):
            raise ValueError(f"{source}: {name}={new.tolist()!r}: must be finite with shape {old.shape}")
        params = _set(params, name, jnp.asarray(new, old.dtype))
    return params


def _tree_values(old, new, where: str):
    """`old`'s tree (nested mappings of arrays) with `new`'s numbers, every key, shape and number checked."""
    if isinstance(old, Mapping):
        if not isinstance(new, Mapping) or set(new) != set(old):
            raise ValueError(f"{where}: expected the keys {sorted(old)}")
        return {k: _tree_values(old[k], new[k], f"{where}.{k}") for k in old}
    try:
        arr = np.asarray(new, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: must be an array of numbers") from None
    if arr.shape != np.shape(old) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{where}: must be finite with shape {np.shape(old)}")
    return jnp.asarray(arr, jnp.asarray(old).dtype)


def summed_up(v):
    """A field's value for a record: a number or nested lists as they are; a pytree field (a reflex layer's
    weights) as its size, its thousands of numbers left to the params preset."""
    if isinstance(v, Mapping):
        return f"{sum(np.size(x) for x in jax.tree_util.tree_leaves(v)):,} numbers (a learned reflex layer)"
    return np.asarray(v).tolist()


def load_values(path: str) -> Dict[str, Any]:
    """Param values by name: a params preset (configs/params/<name>.yaml, or a .yaml path: its `values`
    mapping), a `hexjax tune` log.json (its picked iterate, "final") or a JSON file of a plain {name: value}
    mapping."""
    import json

    from hexjax.world.files import is_path, read_yaml, resolve

    if not str(path).endswith(".json") and (not is_path(path) or str(path).endswith((".yaml", ".yml"))):
        f = resolve("params", path)  # a wrong name: one line with the nearest preset names
        raw = read_yaml(f)
        d = raw.get("values") if isinstance(raw, dict) else None
        if not isinstance(d, dict) or not d:
            raise ValueError(f"{f}: a params preset needs `values`: a mapping of param names to values")
        return d
    try:
        with open(path) as f:
            d = json.load(f)
    except (OSError, ValueError) as err:
        raise ValueError(f"params={path!r}: cannot read it as JSON ({err})") from None
    d = d.get("final", {}).get("params", d) if isinstance(d, dict) else d
    if not isinstance(d, dict) or not d:
        raise ValueError(f"params={path!r}: expected a tuning log.json or a mapping of param names to values")
    return d


@dataclasses.dataclass(frozen=True)
class ParamSpace:
    """A set of bounded fields of one controller's params pytree. `bounds`: ((path, Bound), ...)."""

    bounds: tuple

    @classmethod
    def from_dict(cls, d: Mapping[str, Bound]) -> "ParamSpace":
        return cls(tuple(sorted(d.items())))

    @property
    def names(self):
        return tuple(n for n, _ in self.bounds)

    def validate(self, params) -> None:
        """Every field exists in `params`, has sane bounds, and its current value lies inside them."""
        if not self.bounds:
            raise ValueError("params: the space is empty, name at least one field to tune")
        for name, b in self.bounds:
            b.validate(name)
            if not _has(params, name):
                raise ValueError(f"params.{name}: unknown parameter for this controller")
            if isinstance(b, Free):
                if not all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree_util.tree_leaves(_get(params, name))):
                    raise ValueError(f"params.{name}: the starting value is not finite")
                continue
            v = np.asarray(_get(params, name), dtype=float)
            hi = math.inf if b.hi is None else b.hi
            if not np.all(np.isfinite(v)) or np.any(v < b.lo) or np.any(v > hi):
                raise ValueError(f"params.{name}={v.tolist()!r}: the starting value is outside [{b.lo}, {hi}]")

    def init(self, params) -> Dict[str, jax.Array]:
        """Unconstrained arrays u (one per field) that map back to `params`' current values."""
        self.validate(params)
        return {name: to_unconstrained(_get(params, name), b) for name, b in self.bounds}

    def apply(self, u: Mapping[str, Any], params):
        """`params` with each tuned field replaced by to_physical(u[field]) (pure, differentiable)."""
        for name, b in self.bounds:
            params = _set(params, name, jax.tree_util.tree_map(lambda x, old: x.astype(jnp.asarray(old).dtype),
                                                               to_physical(u[name], b), _get(params, name)))
        return params

    def physical(self, u: Mapping[str, Any]) -> Dict[str, np.ndarray]:
        """The physical values of u, as numpy, for logs."""
        return {name: jax.tree_util.tree_map(np.asarray, to_physical(u[name], b)) for name, b in self.bounds}


SPACES: Dict[str, Dict[str, Bound]] = {
    # Luneckas 2020: the basic and the overcoming step (Eqs. 5-7), the transfer time and the pad threshold
    "tactile": {
        "step_length": Bound(0.01, 0.08),  # l_i, m; the robot's l_max is 10 cm (Eq. 15)
        "step_height": Bound(0.01, 0.10),  # h_i, m
        "overcome_length": Bound(0.02, 0.10),  # l_k, m; 2 l_i by hand (Eq. 6)
        "overcome_height": Bound(0.02, 0.12),  # h_k, m; H + 2 cm by hand (Eq. 7), h_max 12 cm (Eq. 15)
        "swing_time": Bound(0.2, 3.0),  # one transfer slot, s (sets the gait period T)
        "tactile_threshold": Bound(0.05, 5.0),  # N
    },
    # Yu 2019: linear-converter trims, contact thresholds (Eqs. 8-9), T_s (Eq. 11), regenerated clearance
    "cpg": {
        "lc_trim": Bound(-0.3, 0.3),  # rad, added to the IK-derived g and h of Eq. 6
        "f_contact": Bound(0.5, 50.0),  # N
        "ramp_time": Bound(0.05, 2.0),  # s
        "elevated_clearance": Bound(0.04, 0.12),  # m
        "clearance": Bound(0.02, 0.08),  # m
    },
}


# Fields tuned only where a config names them: the per-leg numbers of the Yu 2019 CPG (`CPGParams.leg_*`), each
# leg's own converter trims, clearance offset and contact-threshold factors (6 x 12 + 6 + 6 x 3 = 96 numbers; the
# paper gives every leg the same). Bounds keep every leg's point within reach and every threshold positive.
PER_LEG: Dict[str, Dict[str, Bound]] = {
    "cpg": {
        "leg_trim": Bound(-0.15, 0.15),  # rad, on top of lc_trim
        "leg_clearance": Bound(-0.01, 0.01),  # m, on clearance and elevated_clearance
        "leg_f_scale": Bound(0.5, 2.0),  # factor on f_contact
    },
}


# The reflex layer over the CPG (`hexjax.control.reflex`): its weights, and the CPG's own fields where a config
# names them (`base.lc_trim`, ...)
SPACES["cpg-reflex"] = {"net": Free()}
PER_LEG["cpg-reflex"] = {f"base.{k}": b for k, b in {**SPACES["cpg"], **PER_LEG["cpg"]}.items()}
# and over the Luneckas 2020 open-loop gait: its weights, and the gait's stroke and swing height where a config
# names them (not its swing time: the walk's length is set from the gait's own pace)
SPACES["gait-reflex"] = {"net": Free()}
PER_LEG["gait-reflex"] = {f"base.{k}": SPACES["tactile"][k] for k in ("step_length", "step_height")}


def make_space(controller: str, overrides: Optional[Mapping[str, Mapping[str, float]]] = None,
               only: Optional[list] = None) -> ParamSpace:
    """The preset space of `controller` (a key of `SPACES`), restricted to `only` (field names) and with
    bounds replaced from `overrides` ({field: {"min": lo, "max": hi}}, as in configs/tune/*.yaml). The per-leg
    fields (`PER_LEG`) join only when `only` names them."""
    if controller not in SPACES:
        raise ValueError(f"controller={controller!r}: choose one of {sorted(SPACES)}")
    known = {**SPACES[controller], **PER_LEG.get(controller, {})}
    for name in list(only or []) + list(overrides or {}):
        if name not in known:
            raise ValueError(f"params.{name}: unknown parameter for controller {controller!r}; "
                             f"tunable: {sorted(known)}")
    base = {k: known[k] for k in only} if only else dict(SPACES[controller])
    for name, o in (overrides or {}).items():
        if not isinstance(o, Mapping):
            raise ValueError(f"params.{name}={o!r}: must be a mapping of min and max")
        if isinstance(known[name], Free):
            if o:
                raise ValueError(f"params.{name}: has no bounds (a network's weights); give it as {{}}")
            base[name] = Free()
            continue
        unknown = set(o) - {"min", "max"}
        if unknown:
            raise ValueError(f"params.{name}: unknown keys {sorted(unknown)}; use min and max")
        for k in ("min", "max"):
            v = o.get(k)
            if k in o and not (v is None and k == "max") and (isinstance(v, bool) or not isinstance(v, (int, float))):
                raise ValueError(f"params.{name}.{k}={v!r}: must be a number")
        lo = float(o.get("min", base.get(name, known[name]).lo))
        hi = o.get("max", base.get(name, known[name]).hi)
        base[name] = Bound(lo, None if hi is None else float(hi))
    for name, b in base.items():
        b.validate(name)
    return ParamSpace.from_dict(base)
