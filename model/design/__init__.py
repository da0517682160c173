"""Inverse design: targets, the search, robust design and the robust library."""
