"""A refactor keeps every number: run `hexjax evaluate --batch 8` and four paper experiments at small sizes on
`validated` physics, and either record their JSON as the reference or compare today's with a recorded set.

    python scripts/same_numbers.py --record out/same_numbers_before     # before the change
    python scripts/same_numbers.py --against out/same_numbers_before    # after it

About 10 minutes on 2 CPU cores from an empty compilation cache, 5 with its programs in the cache. Prints one
line per command and exits 1 when a number differs beyond float32 rounding or a key was removed; keys that only
today's code writes are listed and allowed. Compare on the machine that recorded: on another CPU the obstacle
walks round differently; zhao2018, the planner alone, must still be identical."""

import argparse
import json
import os
import subprocess
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from compare_json import walk  # noqa: E402

COMMANDS = {
    "evaluate": ["evaluate", "--batch", "8"],
    "zhao2018": ["experiment", "zhao2018"],
    "chen2019": ["experiment", "chen2019", "--batch", "2"],
    "luneckas2020": ["experiment", "luneckas2020", "--n", "4", "--distances", "1"],
    "yu2019-step": ["experiment", "yu2019-step"],
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    which = ap.add_mutually_exclusive_group(required=True)
    which.add_argument("--record", help="write the reference JSON into this folder")
    which.add_argument("--against", help="a folder --record wrote: compare today's JSON with it")
    ap.add_argument("--out", default="", help="folder for today's JSON with --against (default: a temporary one)")
    a = ap.parse_args()
    if a.against and not all(os.path.exists(os.path.join(a.against, f"{n}.json")) for n in COMMANDS):
        ap.error(f"--against {a.against}: no recorded set there (run --record first)")
    out = a.record or a.out or tempfile.mkdtemp(prefix="same_numbers_")
    os.makedirs(out, exist_ok=True)
    failed = False
    for name, args in COMMANDS.items():
        path = os.path.join(out, f"{name}.json")
        subprocess.run([sys.executable, "-m", "hexjax.cli", *args, "--json", path], check=True,
                       stdout=subprocess.DEVNULL)
        if a.record:
            print(f"{name}: recorded {path}")
            continue
        with open(os.path.join(a.against, f"{name}.json")) as f, open(path) as g:
            diffs = []
            walk(json.load(f), json.load(g), "", diffs)
        added = [p for k, p, *_ in diffs if k == "added"]
        bad = [d for d in diffs if d[0] not in ("added", "rounding")]
        rounding = sum(d[0] == "rounding" for d in diffs)
        verdict = "differs" if bad else ("equal to float32 rounding" if rounding else "identical")
        print(f"{name}: {verdict}" + (f"; {len(added)} keys added: {', '.join(added)}" if added else ""))
        for row in bad[:10]:
            print("  ", *row)
        failed |= bool(bad)
    print(("recorded in" if a.record else "today's JSON:"), out)
    return int(failed)


if __name__ == "__main__":
    sys.exit(main())
