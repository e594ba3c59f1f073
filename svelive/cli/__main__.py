"""``python -m svelive.cli``: the ``svelive`` command."""

import sys

from svelive.cli import main

if __name__ == "__main__":
    sys.exit(main())
