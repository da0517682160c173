"""The simulated users of the load benchmarks: viser protocol clients, Chromium pages and the processes they run in."""
