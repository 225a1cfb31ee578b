"""``python -m jaxfit``: the command line (``jaxfit.cli``). Guarded, since the batch's
spawned worker processes import the main module again under another name."""

import sys

from .cli import entry

if __name__ == "__main__":
    sys.exit(entry())
