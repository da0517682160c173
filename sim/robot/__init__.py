"""The robot as data: its description, its MuJoCo model, variations of its physics, link poses."""
