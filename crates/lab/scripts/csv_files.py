"""Opening committed result CSVs, plain or gzipped.

Per-episode files larger than 50 KB are committed gzipped (`episodes.csv.gz`, see
docs/results-policy.md); a fresh run writes plain `episodes.csv`. `open_csv` takes either name:
a path ending in `.gz` is gunzipped, and a plain path that is absent is read from the `.gz`
beside it. Imported by the scripts in this directory; scripts elsewhere carry a copy of
`open_csv` (they run standalone from the repository root).
"""

import gzip
import os


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
