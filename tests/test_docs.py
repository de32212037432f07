"""The docs are a user's reference: README.md and docs/*.md state current figures with their command and JSON,
not a run history (no commit hashes, dated run sections or counted sessions; git keeps the history), and
docs/results/ holds exactly the files a document names."""
import os
import re

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
DOCS = ["README.md"] + sorted(os.path.join("docs", f) for f in os.listdir(os.path.join(ROOT, "docs"))
                              if f.endswith(".md"))
RESULTS = os.path.join(ROOT, "docs", "results")

# a word of 7-40 hex digits with at least one letter and one digit: an abbreviated or full commit hash
# (or, after "commit" or "clone of", any 7-40 hex digits: a hash may happen to hold no letter)
HASH = re.compile(r"(?<![\w./-])(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}(?![\w/-])"
                  r"|(?<=commit )[0-9a-f]{7,40}\b|(?<=clone of )[0-9a-f]{7,40}\b")
ORDINAL = (r"(first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|eleventh|twelfth|\w+teenth|"
           r"twenty\w*|thirty\w*|forty\w*|fifty\w*)")
RUN_LOG = [
    (re.compile(r"^#+ .*\d{4}-\d{2}-\d{2}", re.M), "a dated section heading"),
    (re.compile(r"^#+ .*\bsession\b", re.M | re.I), "a section heading naming a session"),
    (re.compile(ORDINAL + r"[ -]sessions?\b", re.I), "a counted session"),
    (re.compile(r"\b(this|last|previous|next) session\b", re.I), "session wording"),
    (re.compile(r"\b(since |in |an? |the )?issue \d+\b|\bthe issue's\b", re.I), "a reference to a work item"),
]


def _read(path):
    with open(os.path.join(ROOT, path), encoding="utf-8") as f:
        return f.read()


def _line(text, pos):
    return text.count("\n", 0, pos) + 1


@pytest.mark.parametrize("path", DOCS)
def test_a_doc_has_no_commit_hash_or_run_log_wording(path):
    text = _read(path)
    found = [f"{path}:{_line(text, m.start())}: commit hash {m.group(0)}" for m in HASH.finditer(text)]
    for rx, what in RUN_LOG:
        found += [f"{path}:{_line(text, m.start())}: {what}: {m.group(0)!r}" for m in rx.finditer(text)]
    assert not found, "\n".join(found[:20]) + (f"\n... {len(found) - 20} more" if len(found) > 20 else "")


def test_the_checker_finds_what_it_is_for():
    """The patterns above catch a hash, a dated heading and a counted session, and pass ordinary prose."""
    assert HASH.search("measured at 15df0a7 on the VM") and HASH.search("(commit 4529341)")
    assert not HASH.search("seed 1234567, 1e-08, the float32 sum, docs/results/bench_gpu_h200.json")
    assert RUN_LOG[0][0].search("## 2026-11-30 (thirty-ninth session), issue 18")
    assert RUN_LOG[2][0].search("in the twenty-fourth session") and RUN_LOG[3][0].search("measured this session")
    assert RUN_LOG[4][0].search("# Planners (issue 6)") and RUN_LOG[4][0].search("the issue's table")
    assert not RUN_LOG[4][0].search("a known issue with Warp 1.18's CPU graphs")
    assert not any(rx.search("## Compile time and the compilation cache\nThe first run compiles, the second loads.")
                   for rx, _ in RUN_LOG)


def test_docs_results_holds_exactly_the_files_the_docs_name():
    """Every file in docs/results is named by README.md or a doc, and every link into docs/results resolves."""
    texts = {p: _read(p) for p in DOCS}
    everything = "\n".join(texts.values())
    files = sorted(f for f in os.listdir(RESULTS) if not f.startswith("."))
    unnamed = [f for f in files if f not in everything]
    assert not unnamed, f"{len(unnamed)} files in docs/results named by no doc: {', '.join(unnamed[:15])}"
    missing = [f"{p}: {m}" for p, t in texts.items()
               for m in re.findall(r"\]\((?:docs/)?results/([^)#\s]+)\)", t)
               if not os.path.exists(os.path.join(RESULTS, m))]
    assert not missing, "links to files docs/results does not have: " + "; ".join(missing)


def test_the_readme_is_a_front_page():
    """README.md: its title, then exactly two commands (`make demo`, `make test`) of at most 120 characters each
    with a comment, at most 90 lines in all, and every doc of docs/ in its list."""
    text = _read("README.md")
    lines = text.splitlines()
    assert lines[0] == "# hexjax" and len(lines) <= 90, len(lines)
    block = re.search(r"```\n(.*?)```", text, re.S).group(1).splitlines()
    assert [ln.split()[:2] for ln in block] == [["make", "demo"], ["make", "test"]], block
    assert all(len(ln) <= 120 and "  # " in ln for ln in block), block
    docs = sorted(f for f in os.listdir(os.path.join(ROOT, "docs")) if f.endswith(".md"))
    missing = [d for d in docs if f"`docs/{d}`" not in text]
    assert not missing, f"docs not in README.md's list: {missing}"
