#!/usr/bin/env python3
"""Estimate soil parameters along a recorded drive (default: the bundled demo recording).

Same as `torchsoil estimate` (see `torchsoil estimate --help`).
"""

import sys

from torchsoil.cli import main

if __name__ == "__main__":
    sys.exit(main(["estimate", *sys.argv[1:]]))
