"""One module per ``pdr-mag`` subcommand, each exposing a click command named ``command``."""
