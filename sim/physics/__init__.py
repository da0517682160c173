"""Running the simulator: rollouts, the command rule, threads, the fair scheduler, backends."""
