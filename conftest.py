"""Puts the repository root on sys.path so tests run without installing the package."""
