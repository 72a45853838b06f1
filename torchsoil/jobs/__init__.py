"""The jobs behind the commands: each takes an input (a recording or a terrain pair), settings
and an output folder, claims the folder (`provenance`), runs the rooms' library calls and
writes the run's outputs. The command line (`torchsoil.cli`) parses its options and calls one
of them.

Modules: `estimate` (`torchsoil estimate`), `diagnose` (`torchsoil diagnose`), `process_bag`
(`torchsoil process-bag`), `fleet` (many recordings on an engine), `study` (`torchsoil study`),
`ablation` (`torchsoil ablation`), `record` (`torchsoil record`), `common` (input loading and the
run record they share) and `provenance` (run.json: what made a folder).
"""
