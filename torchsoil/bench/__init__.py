"""Benchmarks of torchsoil (`torchsoil bench` or `python scripts/bench.py`): every module
contributes its figures through `run(quick) -> dict` (`torchsoil.jobs.bench` runs them and
writes bench.json). Timings, not tests: the test suite never runs them."""
