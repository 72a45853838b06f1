"""`python -m torchsoil` is the `torchsoil` command."""

from torchsoil.cli import main

if __name__ == "__main__":   # a worker process (spawned) imports this module again
    raise SystemExit(main())
