#!/usr/bin/env python3
"""Write a synthetic recording (rosbag2 + robot YAML + truth) or only its terrain pair.

Same as `torchsoil record` (see `torchsoil record --help`).
"""

import sys

from torchsoil.cli import main

if __name__ == "__main__":
    sys.exit(main(["record", *sys.argv[1:]]))
