"""How many envs fit: a batch's memory, estimated from an engine's measured bytes before anything compiles
(`Engine.bytes_per_env`, `Engine.grad_bytes_per_env_step`), against what the accelerators or the host have.
Imports nothing heavy: the command line checks a batch before JAX loads."""

from __future__ import annotations

import os

# the headroom on an engine's measured bytes (`Engine.bytes_per_env`, `Engine.grad_bytes_per_env_step`): traces,
# the terrain's boxes, the allocator's rounding
HEADROOM = 2.0


def available_bytes(host: bool = False) -> int:
    """Memory a batch can use: every local accelerator's limit, or the host's RAM on a CPU or for an engine
    that runs on the host (`host`)."""
    import jax
    devs = jax.local_devices()
    if devs[0].platform != "cpu" and not host:
        return sum(int((d.memory_stats() or {}).get("bytes_limit", 0)) for d in devs)
    return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def check_fits(flag: str, batch: int, per_env: int, what: str, host: bool = False) -> None:
    """One ValueError line naming the largest batch that fits, when `batch` envs of `per_env` bytes each (`what`:
    the job, for the message) need more than `available_bytes(host)`; batches under 1 GB always pass."""
    need = batch * per_env
    if need < 2**30:
        return
    have = available_bytes(host)
    if have and need > have:
        raise ValueError(f"{flag}={batch}: {what} needs about {need / 2**30:,.0f} GiB "
                         f"({per_env // 1024:,} KiB an env), more than the {have / 2**30:,.0f} GiB here; the largest "
                         f"batch that fits is {have // per_env:,}")
