"""Bundled scenario files (package data): the paper's experiments and validation runs."""
