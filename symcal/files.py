"""Writing files: the one home of atomic writes.

Every file symcal writes goes through a temporary file in the destination folder and a
rename, so a reader never sees half a file and an interrupted write leaves the old file
in place.  The new file keeps the mode of the file it replaces, or gets the mode an
ordinary ``open()`` would give it (0666 less the umask), never the 0600 of a temporary
file.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path


def _file_mode(path: Path) -> int:
    """The mode of the file being replaced, else what ``open(path, "w")`` would give."""
    try:
        return path.stat().st_mode & 0o777
    except OSError:
        mask = os.umask(0o022)
        os.umask(mask)
        return 0o666 & ~mask


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file and a rename; return the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.chmod(tmp, _file_mode(path))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def atomic_write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8, newlines as given) to ``path`` atomically; return the path."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def json_text(doc: object) -> str:
    """JSON text of plain data, indented; non-finite numbers become null."""
    def clean(x: object) -> object:
        if isinstance(x, float) and not math.isfinite(x):
            return None
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        return x

    return json.dumps(clean(doc), indent=2) + "\n"
