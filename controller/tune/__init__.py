"""Tuning searches on the plant knowledge and the simulated rig (pure)."""
