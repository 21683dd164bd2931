"""One module per ``mogs`` subcommand: ``HELP``, ``add_arguments(parser)``, ``command(args)``."""
