"""Shared by every volcap package: camera model and rig description, poses, the calibration file
and its colour models, settings with their documentation, bag I/O and frame sets of a bag, the
frame-set synchroniser, the drop-oldest worker, message conversions, QoS and the transport
profile. Imports no other volcap package."""
