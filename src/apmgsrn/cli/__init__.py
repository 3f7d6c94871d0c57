"""Command line: one module per subcommand, wiring only."""
