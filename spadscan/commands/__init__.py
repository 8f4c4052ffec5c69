"""One module per `spadscan` subcommand: `add_arguments(parser)` and `run(args) -> int`, heavy imports inside `run`."""
