"""MJX-Warp on a CPU: record each Warp call once and replay it, instead of running its Python at every step; and
launch the elliptic cone's Hessian kernel in a shape that suits a CPU.

MJX calls MuJoCo Warp through `warp.jax_callable`. On CUDA, Warp records the kernels one call launches as a
graph, keyed by the addresses of the call's buffers, and replays that graph when the same call comes back with
the same buffers. On a CPU, Warp 1.18 runs the Python function at every call instead: it wraps each of the
call's few hundred buffers in a `wp.array`, MJX rebuilds its Model and Data from them, and every kernel is
launched from Python. That is about 8 ms per physics step whatever the batch (measured on the 2-core dev
machine: 9.2 ms for one world, of which the kernels take 0.9 ms), so a CPU walk on Warp was bound by Python.

Warp 1.18 can record CPU graphs as well (`wp.ScopedCapture` on the CPU device, replayed in C++ by
`wp.capture_launch`); its JAX bridge just does not use them. `enable()` makes the bridge do on the CPU what it
does on CUDA: the first call with a given set of buffers (addresses and leading sizes) is recorded and replayed,
later calls with the same buffers are replayed. A physics step inside a rollout's scan sees the same buffers at
every step, so a walk records two graphs per Warp function and replays them. The replay launches the same kernels
with the same arguments, so the results are the same bit for bit (`tests/test_backends.py` checks it). A 6 s walk
of 8 envs took 8.8 s instead of 27.9 s; `hexjax bench --backend warp` ran 13x faster at B = 1, 7.4x at B = 8
and 1.2x at B = 256.

The elliptic friction cone (`PhysicsConfig(cone="elliptic")`, the default of `hexjax robustness`) adds each
contact's cone Hessian to the Newton step's matrix in MuJoCo Warp's `_update_gradient_JTCJ_dense`. It runs one
thread per (contact slot, lower-triangle element of the nv x nv matrix), each thread stopping at once when its slot
holds no contact. On CUDA, MuJoCo Warp launches only a few blocks of slots and lets each thread loop over the rest;
on a CPU it launches every slot, so a CPU launch ran `naconmax` x nv(nv+1)/2 threads one after another: 432 x 300
for 8 Luneckas 2020 worlds (54 contact slots each, about 6 of them touching while the robot stands). That one
kernel was 54 % of a CPU walk's time on Warp (sampled with perf; `tests/test_randomization.py`'s 8-env elliptic
walk). `enable()` also makes a CPU launch of that kernel take the CUDA path's loop with a single block: one
thread per element, looping over the slots in order and stopping at the last contact. Each element sums the same
contacts in the same order as before, so the results are the same bit for bit (`tests/test_backends.py`); the
walk took 21.8 s instead of 64.2 s.

Both reach into Warp's and MuJoCo Warp's private parts (`warp._src.jax.ffi.FfiCallable`, the Hessian kernel's
argument names), so they are applied only to the Warp version they were written against (`KNOWN_VERSIONS`, the
one hexjax's `warp` extra pins) and only while the kernel has the arguments they rewrite; otherwise Warp's own
behaviour is kept. `HEXJAX_WARP_CPU_GRAPHS=off` turns both off as well."""

import collections
import ctypes

from hexjax.cache import switched_off

KNOWN_VERSIONS = ("1.18.0",)
MAX_GRAPHS = 64  # per Warp function; the oldest recording is dropped past it
STATS = collections.Counter()  # 'recorded' and 'replayed' calls, 'hessian' launches reshaped; for tests and the curious
_state = {"on": not switched_off("HEXJAX_WARP_CPU_GRAPHS")}


def set_enabled(on: bool) -> bool:
    """Turn the replay and the Hessian's CPU launch on or off in this process; returns the previous setting. It is
    read when a Warp call runs, and XLA runs a rollout asynchronously: wait for a rollout (`jax.block_until_ready`)
    before switching back. Recordings are made only while on, so each holds the Hessian's CPU launch."""
    before, _state["on"] = _state["on"], bool(on)
    return before


def _address_and_size(buffer):
    return buffer.data, buffer.dims[0] if buffer.rank else 0


def enable() -> bool:
    """Install the CPU replay into Warp's JAX bridge (once per process). Returns whether it is installed."""
    import warp as wp
    from warp._src.jax import ffi as wffi
    cls = wffi.FfiCallable
    if getattr(cls, "_hexjax_cpu_graphs", False):
        return True
    if wp.__version__ not in KNOWN_VERSIONS:
        return False
    original = cls.ffi_callback
    buffers = ctypes.POINTER(ctypes.POINTER(wffi.XLA_FFI_Buffer))

    def ffi_callback(self, call_frame, platform):
        frame = call_frame.contents
        # Warp's own callback answers XLA's first call (its query for the handler's metadata) and reports a call
        # with the wrong number of buffers; it takes Warp's lock itself, so it is called outside that lock
        if (platform != wffi._FFI_PLATFORM_CPU or frame.extension_start or not _state["on"]
                or frame.args.size != self.num_inputs or frame.rets.size != self.num_outputs):
            return original(self, call_frame, platform)
        try:
            with wffi._FFI_CALLBACK_LOCK:
                # the call's one attribute is its id (as in Warp's own callback)
                attr = ctypes.cast(frame.attrs.attrs[0], ctypes.POINTER(wffi.XLA_FFI_Scalar)).contents
                call_id = ctypes.cast(attr.value, ctypes.POINTER(ctypes.c_int64)).contents.value
                ins, outs = ctypes.cast(frame.args.args, buffers), ctypes.cast(frame.rets.rets, buffers)
                # the buffers' addresses and leading sizes: one traced call can serve several batch sizes (a
                # jaxpr cached by JAX and vmapped again), and a recording holds the sizes it was made with
                key = (call_id, *(_address_and_size(ins[i].contents) for i in self.array_input_indices),
                       *(_address_and_size(outs[i].contents) for i in self.array_output_indices))
                capture = self.captures.get(key)
                if capture is None:
                    device = wp.get_device("cpu")
                    wffi._load_ffi_module(wp.get_module(self.func.__module__), device)
                    args = self._build_arg_list(ins, outs, self.call_descriptors[call_id], device)
                    # on the CPU a capture records the launches without running them
                    with wp.ScopedDevice(device), wp.ScopedCapture(device) as capture:
                        self.func(*args)
                    self.captures[key] = capture
                    if len(self.captures) > MAX_GRAPHS:
                        self.captures.popitem(last=False)
                    STATS["recorded"] += 1
                else:
                    self.captures.move_to_end(key)
                    STATS["replayed"] += 1
                wp.capture_launch(capture.graph)
        except Exception as e:  # noqa: BLE001 -- handed to XLA as the call's error, as Warp's callback does
            return wffi.create_ffi_error(frame.api, wffi.XLA_FFI_Error_Code.UNKNOWN,
                                         f"FFI callback error (hexjax's CPU graph replay): {type(e).__name__}: {e}")
        return None

    cls.ffi_callback = ffi_callback
    cls._hexjax_cpu_graphs = True
    _launch_elliptic_hessian_per_element()
    return True


def _launch_elliptic_hessian_per_element() -> bool:
    """Wrap `warp.launch` so that a CPU launch of MuJoCo Warp's `_update_gradient_JTCJ_dense` runs one thread per
    Hessian element, each looping over the contact slots (the module docstring says why). Other kernels, other
    devices and other launch shapes pass through untouched. Returns whether the wrapper is installed."""
    import functools
    import inspect

    import warp as wp
    from mujoco.mjx.third_party.mujoco_warp._src import solver
    kernel = getattr(solver, "_update_gradient_JTCJ_dense", None)
    if kernel is None:
        return False
    if getattr(wp.launch, "_hexjax_hessian", False):
        return True
    names = [a.label for a in kernel.adj.args]
    if not all(n in names for n in ("naconmax_in", "nblocks_perblock", "dim_block")):
        return False
    i_max, i_per, i_dim = names.index("naconmax_in"), names.index("nblocks_perblock"), names.index("dim_block")
    original = wp.launch
    signature = inspect.signature(original)

    @functools.wraps(original)
    def launch(*args, **kwargs):
        if (args[0] if args else kwargs.get("kernel")) is not kernel or not _state["on"]:
            return original(*args, **kwargs)
        call = signature.bind(*args, **kwargs)
        a = call.arguments
        dim, inputs = a["dim"], list(a.get("inputs", ()))
        # MuJoCo Warp's CPU shape: (naconmax, elements) with one slot per thread (nblocks_perblock 1, dim_block
        # naconmax); made (1, elements) with every slot in the thread's loop, in the same order
        if (len(dim) == 2 and len(inputs) > i_dim and inputs[i_per] == 1 and inputs[i_dim] == dim[0] == inputs[i_max]
                and wp.get_device(a.get("device")).is_cpu):
            inputs[i_per], inputs[i_dim] = inputs[i_max], 1
            a["dim"], a["inputs"] = (1, dim[1]), inputs
            STATS["hessian"] += 1
        return original(*call.args, **call.kwargs)

    launch._hexjax_hessian = True
    wp.launch = launch
    return True
