"""Compare two result JSONs of the same command, before and after a change (a refactor keeps
every number; `scripts/same_numbers.py` runs it on five commands).

    python scripts/compare_json.py before.json after.json [rows]

Every number must be equal, or equal to float32 rounding (relative 2e-7, counted apart as 'rounding'); timing
and machine fields are skipped. Prints 'identical', or the kinds of differences and the first `rows` of them
(default 15). Exits 1 when something differs beyond rounding or a key was added, removed or changed length."""

import json
import math
import sys

# fields that measure the run or the machine, not the result
IGNORE = {"wall_s", "compile_s", "env_steps_per_s", "us_per_cycle_per_field", "total_wall_s", "first_call_s",
          "run_s", "timing", "device", "train_s", "saved", "compiled"}


def _short(v):
    return "..." if isinstance(v, (dict, list)) else v


def walk(a, b, path, out):
    """Append (kind, path, before, after) for every difference between a and b to out."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if k in IGNORE:
                continue
            if k not in a:
                out.append(("added", f"{path}/{k}", None, _short(b[k])))
            elif k not in b:
                out.append(("removed", f"{path}/{k}", _short(a[k]), None))
            else:
                walk(a[k], b[k], f"{path}/{k}", out)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            out.append(("length", path, len(a), len(b)))
            return
        for i, (x, y) in enumerate(zip(a, b)):
            walk(x, y, f"{path}[{i}]", out)
    elif isinstance(a, bool) or isinstance(b, bool) or not all(isinstance(x, (int, float)) for x in (a, b)):
        if a != b:
            out.append(("differs", path, a, b))
    elif a != b and not (math.isnan(a) and math.isnan(b)):
        tol = 2e-7 * max(abs(a), abs(b)) + 1e-9
        out.append(("rounding" if abs(a - b) <= 8 * tol else "differs", path, a, b))


def main(argv) -> int:
    if len(argv) not in (2, 3):
        print("usage: " + next(ln.strip() for ln in __doc__.splitlines() if "compare_json.py" in ln), file=sys.stderr)
        return 2
    a, b = (json.load(open(p)) for p in argv[:2])
    out = []
    walk(a, b, "", out)
    kinds = {}
    for k, *_ in out:
        kinds[k] = kinds.get(k, 0) + 1
    print(argv[0], "->", argv[1] + ":", "identical" if not out else kinds)
    for row in [r for r in out if r[0] != "rounding"][:int(argv[2]) if len(argv) > 2 else 15]:
        print("  ", *row)
    return int(any(k != "rounding" for k in kinds))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
