"""Gaits as signals: the gait equation and library, spectra, excitation, the structured family."""
