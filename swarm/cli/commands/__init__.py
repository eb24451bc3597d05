"""One module per `swarm` subcommand, each with ``main(argv=None) -> int``."""
