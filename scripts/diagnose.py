#!/usr/bin/env python3
"""Diagnose model mismatch on a drive: locate it, name the physics left out, fit it.

Same as `torchsoil diagnose` (see `torchsoil diagnose --help`).
"""

import sys

from torchsoil.cli import main

if __name__ == "__main__":
    sys.exit(main(["diagnose", *sys.argv[1:]]))
