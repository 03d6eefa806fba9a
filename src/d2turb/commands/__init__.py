"""Subcommands of the ``d2turb`` CLI, one module each (see ``d2turb.cli.COMMANDS``): each parses its options and calls
the library.

Imports marked ``# lazy: see d2turb.commands`` are inside the command's function so that the pipeline (torch, numpy,
OpenCV) loads only when a command runs: ``d2turb --help`` and usage errors start without it."""
