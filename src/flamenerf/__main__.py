"""`python -m flamenerf`: the `flamenerf` command (what `torchrun -m flamenerf` runs)."""

import sys

from flamenerf.cli import main

if __name__ == "__main__":
    sys.exit(main())
