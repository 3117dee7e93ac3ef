#!/usr/bin/env python3
"""The size budget of docs/ and the rules that keep results reviewable (docs/results-policy.md).

Fails (exit 1, one line per breach naming the file and the rule) when:

- area: tracked files under an area of `docs/budget.csv` (a path prefix; `docs/` is the total)
  add up to more than its budget;
- large-file: a tracked file under docs/ is over 2 MB (2^20 bytes) and is not a weight listed in
  `docs/curves/weights.csv` (KNOWN_LARGE below lists any exception, with why);
- weights: a tracked `.bpk` is missing from the manifest, or its size or sha256 differs; a
  manifest row names a file that is not tracked;
- embedded-image: an HTML file under docs/ embeds an image (`data:image/...`);
- script-in-docs: a `.py` or `.sh` file is tracked under docs/ (result scripts live in
  crates/lab/scripts/results/, one folder per result page, where CI lints them with ruff);
- plain-episodes: a plain per-episode CSV (`episodes*.csv`) over 50 KB is tracked under docs/
  (commit it as `gzip -9n`; every reader takes `.csv.gz`);
- test-reads-docs: a test file (tests/, python/tests/, crates/*/tests/) holds a quoted path that
  starts with `docs/` (tests read tests/fixtures/, never results);
- large-image: a PNG under docs/ is over 300 KB (charts are committed quantised: `pngquant
  --quality=70-95 --strip`, which takes a matplotlib or plotters chart to a tenth of its size);
- uncited-image: a PNG or GIF under docs/ that no page names (a markdown page, an HTML report or
  README.md naming it by a path relative to itself or to the repository's root): images are kept where a page shows them;
- link: a relative markdown link in docs/**/*.md, README.md or ARCHITECTURE.md does not resolve
  to a tracked file or a directory holding one (http(s) links and anchors are not checked;
  KNOWN_BROKEN_LINKS lists the existing ones not fixed yet).

Standard library only; reads the git index (`git ls-files`), not the work tree's untracked files.
`--self-test` plants one breach of each kind in a temporary repository and checks each is caught.

    python3 .ci/budget.py [--root DIR]
    python3 .ci/budget.py --self-test
"""

import argparse
import csv
import hashlib
import os
import re
import subprocess
import sys
import tempfile

MIB = 1 << 20
LARGE_BYTES = 2 * MIB
PLAIN_EPISODES_BYTES = 50 * 1024
LARGE_PNG_BYTES = 300 * 1024
IMAGE_SUFFIXES = (".png", ".gif")
IMAGE_NAME = re.compile(r"[\w./@+-]+\.(?:png|gif)\b")
BUDGET = "docs/budget.csv"
MANIFEST = "docs/curves/weights.csv"
MANIFEST_FIELDS = ["path", "name", "role", "config", "seed", "updates", "bytes", "sha256"]

# Tracked files over 2 MB that are not weights, each with a comment saying why it stays. None since
# 2026-12-07 (the three episode GIFs that were over 2 MB were re-encoded to 1.4-1.6 MB).
KNOWN_LARGE: set[str] = set()

# Relative links known not to resolve, as (page, target), each with a comment saying why; fix
# the page, then delete its entry. None when this check was added (2026-12-07): every relative
# link of the checked pages resolved then.
KNOWN_BROKEN_LINKS: set[tuple[str, str]] = set()

TEST_DIRS = re.compile(r"^(tests/|python/tests/|crates/[^/]+/tests/)")
TEST_DOCS_PATH = re.compile(r"""["']docs/""")
EMBEDDED = re.compile(rb"data:image/")
EPISODES = re.compile(r"^episodes[^/]*\.csv$")
SCRIPT_SUFFIXES = (".py", ".sh")
LINK = re.compile(r"!?\[(?:[^\]\\]|\\.)*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^\s*(```|~~~)")


def tracked(root):
    out = subprocess.run(
        ["git", "-C", root, "ls-files", "-z"], check=True, capture_output=True
    ).stdout.decode("utf-8")
    return [p for p in out.split("\0") if p]


def read_budget(root):
    rows = []
    with open(os.path.join(root, BUDGET), newline="", encoding="utf-8") as f:
        lines = [l for l in f if l.strip() and not l.lstrip().startswith("#")]
    for r in csv.DictReader(lines):
        rows.append((r["area"], float(r["max_mb"]), r.get("note", "")))
    return rows


def read_manifest(root):
    path = os.path.join(root, MANIFEST)
    if not os.path.exists(path):
        return None
    with open(path, newline="", encoding="utf-8") as f:
        rd = csv.DictReader(f)
        if rd.fieldnames != MANIFEST_FIELDS:
            return {"__header__": rd.fieldnames}
        return {r["path"]: r for r in rd}


def sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def md_links(text):
    """Relative link targets of a markdown text, outside fenced code blocks and inline code."""
    fenced = False
    for line in text.splitlines():
        if FENCE.match(line):
            fenced = not fenced
            continue
        if fenced:
            continue
        line = re.sub(r"`[^`]*`", "", line)
        for m in LINK.finditer(line):
            t = m.group(1)
            if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", t) or t.startswith("#"):
                continue
            yield t.split("#", 1)[0].split("?", 1)[0]


def check(root):
    """Every breach as (rule, path, message)."""
    errors = []
    files = tracked(root)
    present = [p for p in files if os.path.isfile(os.path.join(root, p))]
    size = {p: os.path.getsize(os.path.join(root, p)) for p in present}
    docs = [p for p in present if p.startswith("docs/")]

    # area budgets
    try:
        budget = read_budget(root)
    except (OSError, KeyError, ValueError) as e:
        return [("area", BUDGET, f"unreadable: {e}")]
    if not any(a == "docs/" for a, _, _ in budget):
        errors.append(("area", BUDGET, "no `docs/` row (the total)"))
    for area, max_mb, _ in budget:
        total = sum(size[p] for p in docs if p.startswith(area))
        if total > max_mb * MIB:
            errors.append(("area", area, f"{total / MIB:.2f} MB tracked, budget {max_mb:g} MB ({BUDGET})"))

    # weights manifest
    manifest = read_manifest(root)
    if manifest is None:
        errors.append(("weights", MANIFEST, "missing"))
        manifest = {}
    elif "__header__" in manifest:
        errors.append(("weights", MANIFEST, f"header {manifest['__header__']} is not {MANIFEST_FIELDS}"))
        manifest = {}
    for p in present:
        if not p.endswith(".bpk"):
            continue
        row = manifest.get(p)
        if row is None:
            errors.append(("weights", p, f"not listed in {MANIFEST}"))
        elif str(size[p]) != row["bytes"] or sha256(os.path.join(root, p)) != row["sha256"]:
            errors.append(("weights", p, f"size or sha256 differs from its row in {MANIFEST}"))
    for p in manifest:
        if p not in size:
            errors.append(("weights", p, f"listed in {MANIFEST} but not tracked"))

    for p in docs:
        name = os.path.basename(p)
        if size[p] > LARGE_BYTES and p not in manifest and p not in KNOWN_LARGE:
            errors.append(("large-file", p, f"{size[p] / MIB:.2f} MB > 2 MB and not a listed weight"))
        if p.endswith((".html", ".htm")):
            with open(os.path.join(root, p), "rb") as f:
                if EMBEDDED.search(f.read()):
                    errors.append(("embedded-image", p, "embeds an image as data:; reference the file beside it"))
        if EPISODES.match(name) and size[p] > PLAIN_EPISODES_BYTES:
            errors.append(("plain-episodes", p, f"{size[p] / 1024:.0f} KB plain; commit it gzipped (gzip -9n)"))
        if p.endswith(SCRIPT_SUFFIXES):
            errors.append(("script-in-docs", p, "a script under docs/; move it to crates/lab/scripts/results/<page>/"))

        if p.endswith(".png") and size[p] > LARGE_PNG_BYTES:
            errors.append(("large-image", p, f"{size[p] / 1024:.0f} KB PNG; quantise it (pngquant --quality=70-95 --strip)"))

    # images only where a page shows them
    named = set()
    for page in present:
        if not (page in ("README.md", "ARCHITECTURE.md") or (page.startswith("docs/") and page.endswith((".md", ".html")))):
            continue
        with open(os.path.join(root, page), encoding="utf-8", errors="replace") as f:
            text = f.read()
        for m in IMAGE_NAME.finditer(text):
            for base in (os.path.dirname(page), ""):
                named.add(os.path.normpath(os.path.join(base, m.group(0))).replace(os.sep, "/"))
    for p in docs:
        if p.endswith(IMAGE_SUFFIXES) and p not in named:
            errors.append(("uncited-image", p, "no page names this image; link it from its page or remove it"))

    # tests read fixtures, not docs/
    for p in present:
        if TEST_DIRS.match(p) and p.endswith((".rs", ".py", ".sh", ".toml")):
            with open(os.path.join(root, p), encoding="utf-8", errors="replace") as f:
                for i, line in enumerate(f, 1):
                    if TEST_DOCS_PATH.search(line):
                        errors.append(("test-reads-docs", f"{p}:{i}", "a quoted path into docs/; use tests/fixtures/"))

    # relative markdown links
    dirs = set()
    for p in files:
        d = os.path.dirname(p)
        while d:
            dirs.add(d)
            d = os.path.dirname(d)
    fileset = set(files)
    pages = [p for p in present if p in ("README.md", "ARCHITECTURE.md") or (p.startswith("docs/") and p.endswith(".md"))]
    for page in pages:
        with open(os.path.join(root, page), encoding="utf-8", errors="replace") as f:
            text = f.read()
        for t in md_links(text):
            if not t:
                continue
            target = os.path.normpath(os.path.join(os.path.dirname(page), t)).replace(os.sep, "/")
            resolves = not target.startswith("../") and (target in fileset or target in dirs)
            if not resolves and (page, t) not in KNOWN_BROKEN_LINKS:
                errors.append(("link", page, f"`{t}` does not resolve to a tracked file"))
    return errors


def self_test():
    """One clean fixture repository passes; each planted breach is caught by its rule."""
    def git(root, *a):
        subprocess.run(["git", "-C", root, *a], check=True, capture_output=True)

    def write(root, path, data):
        full = os.path.join(root, path)
        os.makedirs(os.path.dirname(full), exist_ok=True)
        with open(full, "wb") as f:
            f.write(data if isinstance(data, bytes) else data.encode())

    def fixture(root):
        git(root, "init", "-q")
        weight = b"\x01" * 1000
        write(root, "docs/curves/run/policy.bpk", weight)
        write(root, "docs/budget.csv", "# fixture\narea,max_mb,note\ndocs/,4,total\ndocs/curves/,0.5,curves\n")
        write(root, MANIFEST, ",".join(MANIFEST_FIELDS) + "\n"
              + f"docs/curves/run/policy.bpk,ego-idm,ego actor,,1,10,{len(weight)},{hashlib.sha256(weight).hexdigest()}\n")
        write(root, "docs/page.md", "See [the run](curves/run/policy.bpk), [web](https://x.org/a) and [here](#top).\n")
        write(root, "docs/report/report.html", '<img src="chart.png">')
        write(root, "docs/report/chart.png", b"\x89PNG")
        write(root, "docs/report/episodes.csv", "a,b\n1,2\n")
        write(root, "README.md", "[page](docs/page.md)\n")
        write(root, "tests/t.py", 'FIXTURE = "tests/fixtures/x"\n')

    breaches = {
        "area": lambda r: write(r, "docs/curves/big.txt", b"x" * (MIB // 2 + 1)),
        "large-file": lambda r: write(r, "docs/other/big.bin", b"x" * (LARGE_BYTES + 1)),
        "weights": lambda r: write(r, "docs/curves/run/policy.bpk", b"\x02" * 1000),
        "embedded-image": lambda r: write(r, "docs/report/report.html", '<img src="chart.png"><img src="data:image/png;base64,AAAA">'),
        "plain-episodes": lambda r: write(r, "docs/report/episodes.csv", "a,b\n" + "1,2\n" * 20000),
        "script-in-docs": lambda r: write(r, "docs/report/table.py", "print('a table')\n"),
        "test-reads-docs": lambda r: write(r, "python/tests/test_x.py", 'P = "docs/curves/run"\n'),
        "large-image": lambda r: write(r, "docs/report/chart.png", b"\x89PNG" + b"x" * LARGE_PNG_BYTES),
        "uncited-image": lambda r: write(r, "docs/report/unused.gif", b"GIF89a"),
        "link": lambda r: write(r, "docs/page.md", "See [gone](curves/gone.csv).\n"),
    }
    failed = []
    with tempfile.TemporaryDirectory() as tmp:
        clean = os.path.join(tmp, "clean")
        os.makedirs(clean)
        fixture(clean)
        git(clean, "add", "-A")
        found = check(clean)
        if found:
            failed.append(f"clean fixture: {found}")
        for rule, plant in breaches.items():
            root = os.path.join(tmp, rule)
            os.makedirs(root)
            fixture(root)
            plant(root)
            git(root, "add", "-A")
            rules = {e[0] for e in check(root)}
            if rules != {rule}:
                failed.append(f"planted {rule}: caught {sorted(rules) or 'nothing'}")
            else:
                print(f"self-test: planted {rule} breach caught")
    for f in failed:
        print(f"self-test FAILED: {f}", file=sys.stderr)
    return 1 if failed else 0


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
    ap.add_argument("--self-test", action="store_true")
    a = ap.parse_args()
    if a.self_test:
        return self_test()
    errors = check(os.path.abspath(a.root))
    for rule, path, msg in errors:
        print(f"{path}: {rule}: {msg}", file=sys.stderr)
    if errors:
        print(f"budget: {len(errors)} breach(es); see docs/results-policy.md", file=sys.stderr)
        return 1
    print("budget: docs/ within budget, weights listed, images cited and quantised, none embedded, no large plain episodes, no scripts, tests and links clean")
    return 0


if __name__ == "__main__":
    sys.exit(main())
