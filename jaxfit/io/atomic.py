"""Files written all at once: a temporary file beside the target, renamed onto it only
when it is complete, so a reader (or a run interrupted while writing) sees the old file
or the new one, never a part."""

from __future__ import annotations

import contextlib
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
