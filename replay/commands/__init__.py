"""What each ``cathtrack`` subcommand does once its options are parsed (:mod:`replay.cli`).

One module per command, each with ``run(args) -> int`` (the exit code); :mod:`replay.cli`
imports a command's module only when that command runs.
"""
