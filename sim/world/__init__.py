"""The ground as data: a world description and how it is built into the robot's model."""
