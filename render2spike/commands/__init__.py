"""Subcommands of the ``render2spike`` CLI; one module each, discovered by :mod:`render2spike.cli`."""
