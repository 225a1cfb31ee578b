"""Files written all at once: a temporary file beside the target, renamed onto it only
when it is complete, so a reader (or a run interrupted while writing) sees the old file
or the new one, never a part."""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def replacing(path, *, private: bool = False):
    """Yield a temporary path beside ``path`` (same extension, so writers that go by it
    pick the same format); on leaving the block it is renamed onto ``path``, or removed
    if the block raised. The file gets the user's usual permissions, or only the user's
    with ``private``."""
    path = Path(path)
    fd, temporary = tempfile.mkstemp(prefix=f".{path.stem}.part-", suffix=path.suffix,
                                     dir=path.parent)
    os.close(fd)
    try:
        yield Path(temporary)
        if not private:
            os.chmod(temporary, 0o666 & ~_umask())
        os.replace(temporary, path)
    finally:
        if os.path.exists(temporary):
            os.unlink(temporary)


@contextlib.contextmanager
def replacing_all(directory, names):
    """Yield {name: temporary path} for the files ``names`` in ``directory`` (made if
    missing), each as ``replacing`` gives: renamed into place when the block is left,
    all removed if it raised, so a save that fails leaves the old files."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    with contextlib.ExitStack() as stack:
        yield {name: stack.enter_context(replacing(out / name)) for name in names}


def write_json(path, data, *, indent: int = 1) -> None:
    """Write ``data`` as JSON to ``path`` whole or not at all (``replacing``)."""
    with replacing(path) as part:
        part.write_text(json.dumps(data, indent=indent))
