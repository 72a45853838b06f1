#!/usr/bin/env python3
"""Scripted policies on the soil-traverse environment: damage vs time.

Same as `torchsoil rollout` (see `torchsoil rollout --help`).
"""

import sys

from torchsoil.cli import main

if __name__ == "__main__":
    sys.exit(main(["rollout", *sys.argv[1:]]))
