"""`python -m torchsoil` is the `torchsoil` command."""

from torchsoil.cli import main

raise SystemExit(main())
