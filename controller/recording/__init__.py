"""Recordings (MCAP): writing, reading, reports."""
