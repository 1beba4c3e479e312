"""One module per ``pmcal`` subcommand (or group); each defines ``register(subparsers)``."""
