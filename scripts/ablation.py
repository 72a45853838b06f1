#!/usr/bin/env python3
"""The paper's ablation table on one input.

Same as `torchsoil ablation` (see `torchsoil ablation --help`).
"""

import sys

from torchsoil.cli import main

if __name__ == "__main__":
    sys.exit(main(["ablation", *sys.argv[1:]]))
