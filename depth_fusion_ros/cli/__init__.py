"""The ``depth-fusion`` command: one module per subcommand, each with ``register(subparsers)``."""
