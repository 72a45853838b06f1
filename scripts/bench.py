#!/usr/bin/env python3
"""Benchmarks: print every figure and write out/bench/bench.json.

Same as `torchsoil bench` (see `torchsoil bench --help`).
"""

import sys

from torchsoil.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", *sys.argv[1:]]))
