"""Rig configs, launch file, composed runner and the volcap command line."""
