"""The `neuralslicer` command line: parses options, validates input, starts the flows (outside the core)."""
