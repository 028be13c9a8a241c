"""Writes the other way: commands, the flash guard, feeds, operations and calibrations."""
