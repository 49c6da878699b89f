"""Files written whole or not at all. Each write goes to a temporary file beside its path and is
renamed onto it once complete, so that a run cut short (a killed process, a machine taken back)
never leaves a half-written result that a later stage, a rerun or a cache lookup would take as
complete. Standard library only: every script of the benchmark may import it.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys


@contextlib.contextmanager
def replacing(path: str, mode: str = "w"):
    """A file opened for writing in place of `path`: renamed onto `path` when the block ends
    normally, removed when it raises (`path` is then left as it was)."""
    tmp = f"{path}.{os.getpid()}.tmp"
    try:
        with open(tmp, mode) as f:
            yield f
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def write_json(path: str, value, indent: int | None = 1) -> None:
    """`value` as JSON at `path` (a line of its own), whole or not at all."""
    with replacing(path) as f:
        json.dump(value, f, indent=indent)
        f.write("\n")


def write_text(path: str, text: str) -> None:
    """`text` at `path`, whole or not at all."""
    with replacing(path) as f:
        f.write(text)


def read_json(path: str):
    """What the JSON file at `path` holds, or None where it is missing or unreadable (a file of an
    older version of this code written in place and cut short): a cache miss, not an error."""
    try:
        with open(path) as f:
            return json.load(f)
    except FileNotFoundError:
        return None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        print(f"{path}: unreadable ({e}); measuring again", file=sys.stderr)
        return None
