"""Shared camera model, rig description, poses, message conversions, synchroniser, QoS and transport profile for volcap."""
