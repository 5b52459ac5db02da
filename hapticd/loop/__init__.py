"""The servo loop and what it runs on: the devices' bank, the pacer, the real-time
setup, the loop's commands, events and statistics, mounts and trajectories."""
