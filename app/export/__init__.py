"""Gait files and exports: the gait CSV, ``snakeloco export`` formats, the html replay."""
