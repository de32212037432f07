"""Issue 18's first acceptance item as one command: run `hexjax evaluate --batch 8` and the four paper
experiments at issue 18's sizes, and compare each JSON with the one the pre-refactor commit (3699d70) wrote
(kept in docs/results/pre_refactor_3699d70/).

    python scripts/same_numbers.py [--out DIR]

About 10.5 minutes on 2 CPU cores from an empty compilation cache (another job running beside it), 5 min 19 s
with its programs in the cache. Prints one line per command and exits 1 when a number differs beyond float32
rounding or a key was removed; keys that only today's code writes are listed and allowed. The kept files were
written on an AMD EPYC with AVX-512 (2 cores, jax 0.11.2), with XLA_FLAGS as hexjax sets them now
(docs/benchmarks.md, 2026-11-30, twenty-seventh session). On another CPU the obstacle walks round differently and
differ by more (the 2026-11-26 section's "Numbers"); zhao2018, the planner alone, must still be identical."""

import argparse
import json
import os
import subprocess
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from compare_json import walk  # noqa: E402

KEPT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "docs", "results", "pre_refactor_3699d70")
COMMANDS = {
    "evaluate": ["evaluate", "--batch", "8"],
    "zhao2018": ["experiment", "zhao2018"],
    "chen2019": ["experiment", "chen2019", "--batch", "2"],
    "luneckas2020": ["experiment", "luneckas2020", "--n", "4", "--distances", "1"],
    "yu2019-step": ["experiment", "yu2019-step"],
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="", help="folder for today's JSON (default: a temporary one)")
    out = ap.parse_args().out or tempfile.mkdtemp(prefix="same_numbers_")
    os.makedirs(out, exist_ok=True)
    failed = False
    for name, args in COMMANDS.items():
        path = os.path.join(out, f"{name}.json")
        subprocess.run([sys.executable, "-m", "hexjax.cli", *args, "--json", path], check=True,
                       stdout=subprocess.DEVNULL)
        with open(os.path.join(KEPT, f"{name}.json")) as f, open(path) as g:
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
    print("today's JSON:", out)
    return int(failed)


if __name__ == "__main__":
    sys.exit(main())
