"""What the running gateway knows now, shared: every writer and reader meets here.

The state (latest samples, devices, lines, each sink's and writer's status), the host's
clock and the state directory's health. Below the sinks, the records and the writers, so
that each of them reaches it without reaching another's floor.
"""
