"""Sequence readers: one small module per on-disk format."""
