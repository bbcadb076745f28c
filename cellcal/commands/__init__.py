"""One module per ``cellcal`` subcommand; each exposes a click command."""
