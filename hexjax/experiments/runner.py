"""Run one registry entry (`hexjax.experiments.registry`) from parsed options: check what can be checked before
any work (output paths, preset names), run it, print its report, write its JSON and plots."""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import importlib
import json
import os
import tempfile
import types
from typing import Any, Dict, List

from hexjax.experiments.registry import Entry
from hexjax.interrupt import keep
from hexjax.sim.config import RolloutConfig
from hexjax.sim.memory import HEADROOM, check_fits
from hexjax.world.files import resolve


@contextlib.contextmanager
def step_bar(desc: str, ctrl_dt: float, duration: float, cfg: RolloutConfig = RolloutConfig(), every: int = 50,
             enabled: bool = True):
    """A tqdm bar over one rollout's control steps (settling included), moved from the device every `every`
    steps; yields the `RolloutConfig` to roll out with (`cfg` with `progress_every` set, or `cfg` itself when
    the bar is off: a program without the host callback is kept on disk, `hexjax.sim.compiled`)."""
    from tqdm.auto import tqdm

    from hexjax.sim.config import control_steps, settle_steps
    from hexjax.sim.step import progress_to
    run_cfg = dataclasses.replace(cfg, progress_every=every) if enabled else cfg
    total = settle_steps(cfg, ctrl_dt) + control_steps(duration, ctrl_dt)
    bar = tqdm(total=total, desc=desc, unit="step", disable=not enabled, mininterval=1.0)
    with progress_to(lambda i: bar.update(i - bar.n)):
        yield run_cfg
    bar.update(total - bar.n)
    bar.close()


def check_folder(flag: str, value, folder: str) -> None:
    """Make `folder` and write a file there and remove it, or raise one ValueError line naming `flag` and
    `value`. A real write, because `os.access` tells root that /proc and similar folders are writable."""
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError as err:
        raise ValueError(f"{flag}={value!r}: cannot make its folder ({err.strerror})") from None
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".hexjax-probe-"):
            pass
    except OSError as err:
        raise ValueError(f"{flag}={value!r}: cannot write in its folder {folder} ({err.strerror})") from None


def check_options(entry: Entry, o: types.SimpleNamespace) -> None:
    """Raise one ValueError line for an output path with the wrong suffix, naming a folder, or in a folder that
    cannot be made or written, an input file that is not there, or a preset name that does not resolve, before
    anything runs."""
    for opt in entry.options:
        v = getattr(o, opt.name)
        if opt.output and v:
            if not str(v).lower().endswith(opt.output):
                raise ValueError(f"{opt.flag}={v!r}: the file must end in {' or '.join(opt.output)}")
            if os.path.isdir(v):
                raise ValueError(f"{opt.flag}={v!r}: a folder is there; give a file path")
            check_folder(opt.flag, v, os.path.dirname(os.path.abspath(v)))
        for f in (v if isinstance(v, list) else [v]) if opt.input and v else []:
            if not str(f).lower().endswith(opt.input):
                raise ValueError(f"{opt.flag}={f!r}: the file must end in {' or '.join(opt.input)}")
            if not os.path.isfile(f):
                raise ValueError(f"{opt.flag}={f!r}: no such file" + (f" ({opt.help})" if opt.help else ""))
        if opt.preset and v:
            for name in (v if isinstance(v, list) else [v]):
                resolve(opt.preset, name)


def _write_whole(path, payload) -> None:
    """`payload` as JSON at `path`, whole or not at all (a temporary file renamed over it, so an interrupt never
    leaves half a file)."""
    tmp = f"{path}.tmp"
    with open(tmp, "w") as f:
        json.dump(payload, f, default=float)
    os.replace(tmp, path)


def write_partial(path: str, payload, text: str) -> None:
    """Write a resumable run's partial file whole or not at all, and `keep` `text`."""
    _write_whole(path, payload)
    keep(text)


def _kept_path(kind: str, digest: str, key: str):
    from hexjax.cache import cache_dir
    d = cache_dir()
    return None if d is None else d / kind / digest / (hashlib.sha256(key.encode()).hexdigest()[:16] + ".json")


def read_kept(kind: str, digest: str, keys, have: Dict) -> Dict:
    """The finished pieces of `keys` that a run of `kind` with the same `digest` kept in the cache (`keep_piece`),
    leaving out those in `have`, saying how many were reused; {} with the cache off."""
    out = {}
    for k in keys:
        f = _kept_path(kind, digest, k)
        if k not in have and f is not None and f.is_file():
            try:
                out[k] = json.loads(f.read_text())
            except (OSError, ValueError):  # a file another version wrote or a damaged one: run it again
                continue
    if out:
        print(f"{kind}: reused {len(out)} finished pieces kept in {_kept_path(kind, digest, '').parent}", flush=True)
    return out


def keep_piece(kind: str, digest: str, key: str, piece) -> None:
    """Keep one finished piece of a run in the cache (whole or not at all), for any later run with the same
    `digest`: unlike the partial file, it outlives the run's JSON."""
    f = _kept_path(kind, digest, key)
    if f is not None:
        f.parent.mkdir(parents=True, exist_ok=True)
        _write_whole(f, piece)


def read_partial(path: str, digest: str, key: str, name: str, unit: str, total: int, wanted=None) -> Dict:
    """The finished pieces (`payload[key]`) a partial file holds for the same run (its `digest`), saying how
    many of `total` it resumes (of the pieces named in `wanted`, where given); {} when there is none or it
    belongs to another run."""
    if not path or not os.path.exists(path):
        return {}
    with open(path) as f:
        saved = json.load(f)
    if saved.get("digest") != digest:
        return {}
    done = saved[key]
    n = len(done) if wanted is None else sum(w in done for w in wanted)
    print(f"{name}: resumed {n} of {total} {unit} from {path}", flush=True)
    return done


def write_json(path: str, obj) -> None:
    """`obj` without its `_`-keys (arrays kept for plots) as indented JSON; numpy numbers as floats."""
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w") as f:
        json.dump({k: v for k, v in obj.items() if not str(k).startswith("_")}, f, indent=2, default=float)


# the estimate when no engine is chosen yet (the engine's own figure has `HEADROOM` on it)
PER_ENV_BYTES = 512 * 1024


def check_batch_memory(o: types.SimpleNamespace, engine=None) -> None:
    """One ValueError line, naming the largest batch that fits, when `--batch` (envs a row or cell) cannot fit
    where `engine` runs (its measured bytes per env with `HEADROOM`; without an engine a generous
    `PER_ENV_BYTES`), before terrains are drawn or anything compiles."""
    batch = getattr(o, "batch", None)
    if not isinstance(batch, int):
        return
    per_env = PER_ENV_BYTES if engine is None else int(HEADROOM * engine.bytes_per_env)
    what = "a rollout of that many envs" + ("" if engine is None else f" on {engine.title}")
    check_fits("--batch", batch, per_env, what, host=engine is not None and engine.host_only)


def run(entry: Entry, o: types.SimpleNamespace) -> Dict[str, Any]:
    """Check, run, report; write `o.json` and plot to `o.png` where the entry has those options. Returns the
    result and prints what was written."""
    check_options(entry, o)
    check_batch_memory(o)  # the generous estimate, before JAX loads; the chosen engine's figure below
    mod = importlib.import_module(entry.entry)
    if hasattr(mod, "prepare"):  # checks that need no JAX and settings made before it loads
        mod.prepare(o, entry)
    physics = None
    if entry.physics_by == "command" and isinstance(o.physics, list):  # bench times each preset on each engine
        from hexjax.sim.physics import get_physics, timed_settings
        for p in [get_physics(n) for n in o.physics]:  # a bad file or value: one line, before anything runs
            for e in o.engine or [None]:
                print(timed_settings(p, e).header(), flush=True)
    if entry.physics_by == "runner":
        from hexjax.sim.physics import pick
        # the physics is chosen here, once: the fastest engine certified for the preset on this host that can
        # do what the command needs (`NEEDS`), or the one --engine names; the command runs it as given
        physics = pick(o.physics, getattr(o, "engine", "") or None, needs=getattr(mod, "NEEDS", frozenset()))
        check_batch_memory(o, physics.engine)
        print(physics.header(), flush=True)
        o = types.SimpleNamespace(**{**vars(o), "physics": physics})
    res = mod.run(o, entry)
    if physics is not None and isinstance(res, dict):  # every result names the physics it ran
        res.setdefault("physics", physics.record())
    print(mod.report(res))
    written: List[str] = []
    if getattr(o, "png", "") and hasattr(mod, "plot"):
        written += list(mod.plot(res, o.png) or [o.png])
    if getattr(o, "json", ""):
        write_json(o.json, res)
        written.append(o.json)
        lead = not isinstance(res, dict) or res.get("process", 0) == 0  # the process that keeps the partial file
        if lead and os.path.exists(o.json + ".partial.json"):  # the finished pieces are in the result now
            os.remove(o.json + ".partial.json")
    for w in written:
        print(f"wrote {w}")
    return res
