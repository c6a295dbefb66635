"""One module per ``cncgw`` command."""
