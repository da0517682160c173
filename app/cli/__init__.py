"""The console script: subcommands, their options and the reports they print."""
