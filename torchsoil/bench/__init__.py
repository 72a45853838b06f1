"""Benchmarks of torchsoil (`torchsoil bench` or `python scripts/bench.py`): every module
contributes its figures through `run(quick) -> dict`. Not part of the installed library."""
