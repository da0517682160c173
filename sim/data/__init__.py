"""Datasets: generation chunk by chunk, the file format, its reader and writer."""
