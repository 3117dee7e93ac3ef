"""Opening committed result CSVs, plain or gzipped, and writing a script's JSON results.

Per-episode files larger than 50 KB are committed gzipped (`episodes.csv.gz`, see
docs/results-policy.md); a fresh run writes plain `episodes.csv`. `open_csv` takes either name:
a path ending in `.gz` is gunzipped, and a plain path that is absent is read from the `.gz`
beside it. `REPO` is the repository root, for scripts whose default inputs are committed results
under `REPO / "docs"`.

Imported by the scripts in this directory and by those in `results/` (one folder per result page),
which put this directory on `sys.path` first:

    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # crates/lab/scripts
    from csv_files import open_csv
"""

import gzip
import json
import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[3]


def csv_path(path):
    """`path`, or `path + ".gz"` when only the gzipped file is stored."""
    path = os.fspath(path)
    if not path.endswith(".gz") and not os.path.exists(path) and os.path.exists(path + ".gz"):
        return path + ".gz"
    return path


def open_csv(path):
    """A text stream of the CSV at `path` (see `csv_path`), for `csv.DictReader`."""
    path = csv_path(path)
    if path.endswith(".gz"):
        return gzip.open(path, "rt", newline="", encoding="utf-8")
    return open(path, newline="", encoding="utf-8")


def write_json(path, obj):
    """`obj` as indented JSON with a final newline: the form every script here writes."""
    with open(path, "w", encoding="utf-8") as f:
        json.dump(obj, f, indent=1)
        f.write("\n")
