#!/usr/bin/env python3
"""Lidar pipeline: a recording in, a terrain pair, the trajectory and heightmap PNGs out.

Same as `torchsoil process-bag` (see `torchsoil process-bag --help`).
"""

import sys

from torchsoil.cli import main

if __name__ == "__main__":
    sys.exit(main(["process-bag", *sys.argv[1:]]))
