"""The `hexjax` command, built from the registry (configs/commands/*.yaml, configs/experiments/*.yaml): one
subcommand per command, `hexjax experiment NAME` per experiment, each with its own flags. No experiment logic
lives here, and nothing of JAX is imported before the arguments parse (`--help` answers at once)."""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import types

from hexjax.experiments.registry import Entry, Option, commands, experiment, experiments
from hexjax.world.files import is_path, preset_names


def _value_parser(opt: Option):
    """The argparse `type` of an option: one value of its type within its bounds (so that an out-of-range number
    fails as the arguments parse, before JAX is imported), or a comma list of them for a list default (each item
    one of `choices`, where given)."""
    def one(s):
        v = opt.value_type(s)  # a ValueError here: argparse's "invalid int value: 'x'"
        try:
            return opt.check_value(v)
        except ValueError as err:
            raise argparse.ArgumentTypeError(str(err)) from None
    one.__name__ = opt.value_type.__name__
    if not isinstance(opt.default, list) or opt.repeat:
        return one

    def items(s):
        vals = []
        for x in filter(None, (x.strip() for x in s.split(","))):
            try:
                vals.append(one(x))
            except ValueError:
                raise argparse.ArgumentTypeError(f"{x!r} in {s!r}: not a value of type {one.__name__}") from None
        if not vals and opt.default:  # an empty list only where the default is one ('terrain --difficulty')
            raise argparse.ArgumentTypeError(f"{s!r}: give at least one value")
        twice = [v for i, v in enumerate(vals) if v in vals[:i]]
        if twice:  # the same walk, panel or category again
            raise argparse.ArgumentTypeError(f"{twice[0]!r} given twice in {s!r}")
        bad = [v for v in vals if opt.choices and v not in opt.choices]
        if bad:
            raise argparse.ArgumentTypeError(f"{bad[0]!r} is not one of {', '.join(map(str, opt.choices))}")
        return vals

    return items


def _help(opt: Option) -> str:
    text = opt.help
    if opt.preset:
        text += f" (presets: {', '.join(preset_names(opt.preset))}; or a .yaml path)"
    if opt.choices:  # "" (a flag's "pick for me") is said by the help text, not listed
        text += f" (one of: {', '.join(str(c) for c in opt.choices if c != '')})"
    if opt.bounds_text():
        text += f" ({opt.bounds_text()})"
    d = ",".join(map(str, opt.default)) if isinstance(opt.default, list) else opt.default
    return f"{text} [default: {d if d not in ('', None) else 'none'}]".strip()


def _add_options(p: argparse.ArgumentParser, entry: Entry) -> None:
    for opt in entry.options:
        if isinstance(opt.default, bool):
            p.add_argument(opt.flag, dest=opt.name, action="store_true", default=opt.default, help=opt.help)
            continue
        if opt.repeat:
            p.add_argument(opt.flag, dest=opt.name, action="append", default=[], help=opt.help, metavar="VALUE")
            continue
        kw = dict(dest=opt.name, default=opt.default, type=_value_parser(opt), help=_help(opt),
                  metavar=opt.name.upper())
        if opt.choices and not isinstance(opt.default, list):
            kw["choices"] = list(opt.choices)
        p.add_argument(opt.flag, **kw)


def _list_experiments() -> str:
    rows = [(e.name, e.paper, e.summary) for e in experiments().values()]
    w = max(len(r[0]) for r in rows)
    return "\n".join(f"{n:<{w}}  {paper:<15} {s}" for n, paper, s in rows)


def build_parser(argv) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="hexjax", description="Batched MJX hexapods on randomised terrains: the "
                                "controllers, planners and experiments of Luneckas 2020, Yu 2019, Zhao 2018 and "
                                "Chen 2019. Compiled programs are cached (HEXJAX_CACHE_DIR; =off to disable).")
    from hexjax import __version__
    p.add_argument("--version", action="version", version=f"hexjax {__version__}")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    for name, entry in commands().items():
        c = sub.add_parser(name, help=entry.summary, description=entry.summary)
        _add_options(c, entry)
        c.set_defaults(entry=entry)
    ex = sub.add_parser("experiment", help="paper experiments (--list shows them)",
                        description="Paper experiments; `hexjax experiment NAME --help` shows one's flags.")
    ex.add_argument("--list", action="store_true", help="print every experiment, one line each")
    names = ex.add_subparsers(dest="experiment", metavar="NAME")
    registered = experiments()
    # a YAML file of one's own in place of a name: `hexjax experiment my/variant.yaml ...`
    i = argv.index("experiment") + 1 if "experiment" in argv else None
    if i is not None and i < len(argv) and is_path(argv[i]):
        registered = {**registered, argv[i]: experiment(argv[i])}
    for name, entry in registered.items():
        text = f"{entry.paper}: {entry.summary}"
        e = names.add_parser(name, help=text, description=text)
        _add_options(e, entry)
        e.set_defaults(entry=entry)
    return p


def _interrupted_line(name: str) -> str:
    from hexjax.interrupt import kept
    return f"\n{name}: interrupted; {kept() or 'nothing of this run was kept on disk'}"


def _exit_on_ctrl_c(name: str) -> None:
    """Ctrl-C ends the command within a moment, even inside a long compiled call (where Python sees the
    signal only when the call returns): the signal's byte reaches a watching thread through Python's wakeup
    file, which prints what was kept and exits with 130. Files are written whole or not at all
    (`runner.write_partial`), so nothing is left half-written."""
    if threading.current_thread() is not threading.main_thread():
        return
    r, w = os.pipe()
    os.set_blocking(w, False)
    signal.set_wakeup_fd(w)

    def watch():
        while os.read(r, 1) != bytes([signal.SIGINT]):
            pass
        print(_interrupted_line(name), file=sys.stderr, flush=True)
        os._exit(130)

    threading.Thread(target=watch, daemon=True, name="hexjax-ctrl-c").start()


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        a = build_parser(argv).parse_args(argv)
    except ValueError as err:  # a registry file or an experiment path that does not load
        print(f"hexjax: error: {err}", file=sys.stderr)
        return 2
    if a.cmd == "experiment" and a.list:
        print(_list_experiments())
        return 0
    if a.cmd == "experiment" and not a.experiment:
        print("hexjax experiment: error: name an experiment (hexjax experiment --list)", file=sys.stderr)
        return 2
    # XLA logs a "Very slow compile?" alarm (an error line) for long compiles; a user cannot act on it
    os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")
    entry: Entry = a.entry
    opts = types.SimpleNamespace(**{o.name: getattr(a, o.name) for o in entry.options})
    from hexjax.experiments import runner
    name = f"hexjax {a.cmd}{' ' + a.experiment if a.cmd == 'experiment' else ''}"
    if argv is None or argv == sys.argv[1:]:  # the command line, not a caller in Python (tests)
        _exit_on_ctrl_c(name)
    try:
        runner.run(entry, opts)
    except KeyboardInterrupt:
        print(_interrupted_line(name), file=sys.stderr)
        return 130
    except ValueError as err:
        print(f"{name}: error: {err}", file=sys.stderr)
        return 2
    except Exception as err:  # JAX's allocation failure: one line, the sizes to lower, not XLA's stack
        text = str(err)
        if type(err).__name__ != "JaxRuntimeError" or "Out of memory" not in text:
            raise
        need = text[text.index("Out of memory"):].splitlines()[0].rstrip(".")
        print(f"{name}: error: {need} on the device: lower the sizes asked for (envs, fields, polygons) or give "
              "the run a --chunk where it has one", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
