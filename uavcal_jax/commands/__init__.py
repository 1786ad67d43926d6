"""Sub-commands of ``uavcal``; each module has ``register(subparsers)``."""
