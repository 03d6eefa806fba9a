"""Subcommands of the ``d2turb`` CLI, one module each (see ``d2turb.cli.COMMANDS``)."""
