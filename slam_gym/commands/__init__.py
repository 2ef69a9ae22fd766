"""One module per ``slam-gym`` subcommand; each offers ``add_parser(subparsers)``."""
