"""The designer's server: lifecycle, the decode process, viser's internals, workers."""
