"""Depth registration and cleaning for volcap."""
