"""Subcommands of the ``psprm`` command line (one module per group, each exposing ``register``)."""
