#!/usr/bin/env python3
"""Confusion table of the diagnosis over drives with known truth (fixed or randomized synthetic
drives, or foreign terrain pairs: --randomized N --null M, --foreign DIR), in this process or
one task per drive on a process pool or a Ray cluster (--engine local|ray, --workers N).

Same as `torchsoil study` (see `torchsoil study --help`).
"""

import sys

from torchsoil.cli import main

if __name__ == "__main__":
    sys.exit(main(["study", *sys.argv[1:]]))
