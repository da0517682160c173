"""snakeloco application layer: the command-line interface and the browser designer."""
