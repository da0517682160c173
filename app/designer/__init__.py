"""One browser tab of the designer: its state, jobs, GUI, scene and readout."""
